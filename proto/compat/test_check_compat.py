"""Tests of check_compat.py: mutated descriptor sets of the real baseline must fail the
check, additions must pass it, and the CLI must fail on a proto edited and compiled with
protoc."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2 as pb
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import check_compat as cc

settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.register_profile("default", deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "default")

FDP = pb.FieldDescriptorProto
SCALARS = [
    FDP.TYPE_DOUBLE,
    FDP.TYPE_FLOAT,
    FDP.TYPE_INT64,
    FDP.TYPE_UINT64,
    FDP.TYPE_INT32,
    FDP.TYPE_FIXED64,
    FDP.TYPE_FIXED32,
    FDP.TYPE_BOOL,
    FDP.TYPE_STRING,
    FDP.TYPE_BYTES,
    FDP.TYPE_UINT32,
    FDP.TYPE_SFIXED32,
    FDP.TYPE_SFIXED64,
    FDP.TYPE_SINT32,
    FDP.TYPE_SINT64,
]


def newest_baseline() -> pb.FileDescriptorSet:
    files = cc.baselines()
    assert files, "no baseline committed in proto/compat"
    return cc.load(files[-1])


def with_enums_and_reservations(fds: pb.FileDescriptorSet) -> pb.FileDescriptorSet:
    """The baseline plus what the real proto has none of yet: a top-level and a nested enum,
    and reserved numbers and names in a message and an enum."""
    out = pb.FileDescriptorSet()
    out.CopyFrom(fds)
    f = out.file[0]
    mode = f.enum_type.add(name="Mode")
    for i, name in enumerate(["MODE_UNSPECIFIED", "MODE_A", "MODE_B", "MODE_C"]):
        mode.value.add(name=name, number=i)
    mode.reserved_range.add(start=10, end=12)  # inclusive: 10, 11, 12
    mode.reserved_name.append("MODE_OLD")
    host = f.message_type[0]
    kind = host.enum_type.add(name="Kind")
    kind.value.add(name="KIND_UNSPECIFIED", number=0)
    kind.value.add(name="KIND_X", number=1)
    host.reserved_range.add(start=50, end=53)  # exclusive: 50, 51, 52
    host.reserved_name.append("old_field")
    return out


BASE = newest_baseline()
RICH = with_enums_and_reservations(BASE)


def copy(fds: pb.FileDescriptorSet) -> pb.FileDescriptorSet:
    out = pb.FileDescriptorSet()
    out.CopyFrom(fds)
    return out


def all_messages(fds: pb.FileDescriptorSet) -> list[tuple[str, pb.DescriptorProto]]:
    """Every message (nested ones included) with its fully qualified name, mutable."""
    found: list[tuple[str, pb.DescriptorProto]] = []

    def walk(scope: str, msgs: list[pb.DescriptorProto]) -> None:
        for m in msgs:
            found.append((f"{scope}.{m.name}", m))
            walk(f"{scope}.{m.name}", list(m.nested_type))

    for f in fds.file:
        walk(f.package, list(f.message_type))
    return found


def all_fields(fds: pb.FileDescriptorSet) -> list[tuple[str, pb.DescriptorProto, int]]:
    return [(name, m, i) for name, m in all_messages(fds) for i in range(len(m.field))]


Draw = st.DataObject
Mutation = Callable[[pb.FileDescriptorSet, Draw], str]


def pick_field(fds: pb.FileDescriptorSet, data: Draw) -> tuple[str, pb.DescriptorProto, int]:
    return data.draw(st.sampled_from(all_fields(fds)))


def where(name: str, f: pb.FieldDescriptorProto) -> str:
    return f"field {name}.{f.name} = {f.number}"


def remove_field(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, m, i = pick_field(fds, data)
    f = m.field[i]
    expected = f"{where(name, f)} was removed"
    del m.field[i]
    return expected


def renumber_field(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, m, i = pick_field(fds, data)
    f = m.field[i]
    expected = where(name, f)
    used = {g.number for g in m.field}
    f.number = data.draw(st.integers(1, 10_000).filter(lambda n: n not in used))
    return f"{expected} was renumbered to {f.number}"


def rename_field(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, m, i = pick_field(fds, data)
    f = m.field[i]
    expected = where(name, f)
    f.name = f.name + data.draw(st.sampled_from(["_v2", "x", "_old"]))
    return f"{expected} was renamed to {f.name}"


def retype_field(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, m, i = pick_field(fds, data)
    f = m.field[i]
    expected = f"{where(name, f)} changed type"
    if f.type == FDP.TYPE_MESSAGE:
        others = [n for n, _ in all_messages(fds) if f".{n}" != f.type_name]
        f.type_name = "." + data.draw(st.sampled_from(others))
    else:
        f.type = data.draw(st.sampled_from([t for t in SCALARS if t != f.type]))
    return expected


def relabel_field(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, m, i = pick_field(fds, data)
    f = m.field[i]
    expected = f"{where(name, f)} changed label"
    if f.label == FDP.LABEL_REPEATED:
        f.label = FDP.LABEL_OPTIONAL
    else:
        f.label = FDP.LABEL_REPEATED
        f.proto3_optional = False
    return expected


def toggle_presence(fds: pb.FileDescriptorSet, data: Draw) -> str:
    singular = [(n, m, i) for n, m, i in all_fields(fds) if m.field[i].label != FDP.LABEL_REPEATED]
    name, m, i = data.draw(st.sampled_from(singular))
    f = m.field[i]
    f.proto3_optional = not f.proto3_optional
    return f"{where(name, f)} changed label"


def leave_oneof(fds: pb.FileDescriptorSet, data: Draw) -> str:
    in_oneof = [
        (n, m, i)
        for n, m, i in all_fields(fds)
        if m.field[i].HasField("oneof_index") and not m.field[i].proto3_optional
    ]
    name, m, i = data.draw(st.sampled_from(in_oneof))
    f = m.field[i]
    f.ClearField("oneof_index")
    return f"{where(name, f)} moved from oneof"


def remove_message(fds: pb.FileDescriptorSet, data: Draw) -> str:
    name, _ = data.draw(st.sampled_from(all_messages(fds)))
    scope, _, short = name.rpartition(".")
    parents = dict(all_messages(fds))
    container = parents[scope].nested_type if scope in parents else fds.file[0].message_type
    index = next(i for i, m in enumerate(container) if m.name == short)
    del container[index]
    return f"message {name} was removed"


def pick_rpc(fds: pb.FileDescriptorSet, data: Draw) -> tuple[str, pb.MethodDescriptorProto]:
    service = fds.file[0].service[0]
    method = data.draw(st.sampled_from(list(service.method)))
    return f"rpc {fds.file[0].package}.{service.name}.{method.name}", method


def remove_rpc(fds: pb.FileDescriptorSet, data: Draw) -> str:
    where_, method = pick_rpc(fds, data)
    methods = fds.file[0].service[0].method
    del methods[list(methods).index(method)]
    return f"{where_} was removed"


def retype_rpc(fds: pb.FileDescriptorSet, data: Draw) -> str:
    where_, method = pick_rpc(fds, data)
    side = data.draw(st.sampled_from(["input_type", "output_type"]))
    others = [n for n, _ in all_messages(fds) if f".{n}" != getattr(method, side)]
    setattr(method, side, "." + data.draw(st.sampled_from(others)))
    return f"{where_} changed from"


def restream_rpc(fds: pb.FileDescriptorSet, data: Draw) -> str:
    where_, method = pick_rpc(fds, data)
    side = data.draw(st.sampled_from(["client_streaming", "server_streaming"]))
    setattr(method, side, not getattr(method, side))
    return f"{where_} changed from"


def remove_service(fds: pb.FileDescriptorSet, _data: Draw) -> str:
    f = fds.file[0]
    name = f"service {f.package}.{f.service[0].name} was removed"
    del f.service[0]
    return name


def change_package(fds: pb.FileDescriptorSet, _data: Draw) -> str:
    fds.file[0].package = "tamrm.v2"
    return "changed package from tamrm.v1 to tamrm.v2"


def change_codegen_option(fds: pb.FileDescriptorSet, data: Draw) -> str:
    options = fds.file[0].options
    present = {fd.name: v for fd, v in options.ListFields()}
    option = data.draw(st.sampled_from([o for o in cc.CODEGEN_OPTIONS if o in present]))
    if data.draw(st.booleans()):
        options.Clear()
        for name, value in present.items():
            if name != option:
                setattr(options, name, value)
    elif isinstance(present[option], bool):
        setattr(options, option, not present[option])
    else:
        setattr(options, option, f"{present[option]}.moved")
    return f"changed option {option}"


def remove_enum_value(fds: pb.FileDescriptorSet, data: Draw) -> str:
    enum, fq = data.draw(st.sampled_from(enums(fds)))
    i = data.draw(st.integers(0, len(enum.value) - 1))
    expected = f"enum value {fq}.{enum.value[i].name} = {enum.value[i].number} was removed"
    del enum.value[i]
    return expected


def renumber_enum_value(fds: pb.FileDescriptorSet, data: Draw) -> str:
    enum, fq = data.draw(st.sampled_from(enums(fds)))
    v = data.draw(st.sampled_from(list(enum.value)))
    expected = f"enum value {fq}.{v.name} = {v.number} was renumbered"
    used = {w.number for w in enum.value}
    v.number = data.draw(st.integers(-100, 100).filter(lambda n: n not in used))
    return expected


def remove_enum(fds: pb.FileDescriptorSet, data: Draw) -> str:
    f = fds.file[0]
    if data.draw(st.booleans()):
        del f.enum_type[0]
        return "enum tamrm.v1.Mode was removed"
    del f.message_type[0].enum_type[0]
    return f"enum tamrm.v1.{f.message_type[0].name}.Kind was removed"


def unreserve(fds: pb.FileDescriptorSet, data: Draw) -> str:
    f = fds.file[0]
    choice = data.draw(st.integers(0, 3))
    if choice == 0:
        f.enum_type[0].reserved_range[0].end = 11
        return "enum tamrm.v1.Mode no longer reserves numbers 12"
    if choice == 1:
        del f.enum_type[0].reserved_name[:]
        return "enum tamrm.v1.Mode no longer reserves names ['MODE_OLD']"
    host = f.message_type[0]
    if choice == 2:
        host.reserved_range[0].start = 51
        return f"message tamrm.v1.{host.name} no longer reserves field numbers 50"
    del host.reserved_name[:]
    return f"message tamrm.v1.{host.name} no longer reserves field names ['old_field']"


def enums(fds: pb.FileDescriptorSet) -> list[tuple[pb.EnumDescriptorProto, str]]:
    f = fds.file[0]
    host = f.message_type[0]
    return [(f.enum_type[0], "tamrm.v1.Mode"), (host.enum_type[0], f"tamrm.v1.{host.name}.Kind")]


BREAKING: list[Mutation] = [
    remove_field,
    renumber_field,
    rename_field,
    retype_field,
    relabel_field,
    toggle_presence,
    leave_oneof,
    remove_message,
    remove_rpc,
    retype_rpc,
    restream_rpc,
    remove_service,
    change_package,
    change_codegen_option,
    remove_enum_value,
    renumber_enum_value,
    remove_enum,
    unreserve,
]


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(mutation=st.sampled_from(BREAKING), data=st.data())
def test_every_breaking_mutation_is_reported(mutation: Mutation, data: Draw) -> None:
    current = copy(RICH)
    expected = mutation(current, data)
    breaks = cc.breaking_changes(RICH, current)
    assert any(expected in line for line in breaks), (expected, breaks)


def add_field(fds: pb.FileDescriptorSet, data: Draw) -> None:
    _, m = data.draw(st.sampled_from(all_messages(fds)))
    used = {f.number for f in m.field} | {
        n for r in m.reserved_range for n in range(r.start, r.end)
    }
    names = {f.name for f in m.field}
    number = data.draw(st.integers(1, 10_000).filter(lambda n: n not in used))
    name = data.draw(st.from_regex(r"\A[a-z][a-z0-9_]{0,12}\Z").filter(lambda n: n not in names))
    field = m.field.add(name=name, number=number, type=data.draw(st.sampled_from(SCALARS)))
    field.label = data.draw(st.sampled_from([FDP.LABEL_OPTIONAL, FDP.LABEL_REPEATED]))


def add_message(fds: pb.FileDescriptorSet, data: Draw) -> None:
    names = {n for n, _ in all_messages(fds)}
    name = data.draw(st.from_regex(r"\A[A-Z][A-Za-z0-9]{0,12}\Z"))
    if f"tamrm.v1.{name}" not in names:
        fds.file[0].message_type.add(name=name).field.add(
            name="x", number=1, type=FDP.TYPE_UINT32, label=FDP.LABEL_OPTIONAL
        )


def add_rpc(fds: pb.FileDescriptorSet, data: Draw) -> None:
    service = fds.file[0].service[0]
    msgs = ["." + n for n, _ in all_messages(fds)]
    service.method.add(
        name=f"New{len(service.method)}",
        input_type=data.draw(st.sampled_from(msgs)),
        output_type=data.draw(st.sampled_from(msgs)),
        client_streaming=data.draw(st.booleans()),
        server_streaming=data.draw(st.booleans()),
    )


def add_enum_value(fds: pb.FileDescriptorSet, data: Draw) -> None:
    enum, _ = data.draw(st.sampled_from(enums(fds)))
    used = {v.number for v in enum.value} | set(range(10, 13))
    enum.value.add(
        name=f"{enum.name.upper()}_NEW{len(enum.value)}",
        number=data.draw(st.integers(0, 1000).filter(lambda n: n not in used)),
    )


def add_reservation(fds: pb.FileDescriptorSet, data: Draw) -> None:
    _, m = data.draw(st.sampled_from(all_messages(fds)))
    start = data.draw(st.integers(20_000, 30_000))
    m.reserved_range.add(start=start, end=start + data.draw(st.integers(1, 5)))
    m.reserved_name.append(f"gone_{start}")


def add_service(fds: pb.FileDescriptorSet, _data: Draw) -> None:
    name = f"Extra{len(fds.file[0].service)}"
    fds.file[0].service.add(name=name).method.add(
        name="Ping", input_type=".tamrm.v1.GetTaskRequest", output_type=".tamrm.v1.Task"
    )


ADDITIVE = [add_field, add_message, add_rpc, add_enum_value, add_reservation, add_service]


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(mutations=st.lists(st.sampled_from(ADDITIVE), max_size=6), data=st.data())
def test_additions_are_not_breaks(mutations: list[Callable[..., None]], data: Draw) -> None:
    current = copy(RICH)
    for mutation in mutations:
        mutation(current, data)
    assert cc.breaking_changes(RICH, current) == []


spans = st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)).map(sorted).map(tuple))


@given(old=spans, new=spans)
def test_unreserved_spans_match_a_set_model(
    old: list[tuple[int, int]], new: list[tuple[int, int]]
) -> None:
    def numbers(s: list[tuple[int, int]]) -> set[int]:
        return {n for a, b in s for n in range(a, b + 1)}

    left = cc._unreserved(old, new)
    assert numbers(left) == numbers(old) - numbers(new)
    assert all(a <= b for a, b in left)


def test_the_current_proto_is_compatible_with_every_baseline(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert cc.main([]) == 0, capsys.readouterr().out


def edited_proto(tmp_path: Path, old: str, new: str) -> Path:
    """proto/ copied to tmp_path with one edit to shaping.proto, compiled with protoc."""
    src = (cc.PROTO_ROOT / cc.PROTO_FILES[0]).read_text()
    assert src.count(old) == 1, old
    target = tmp_path / "proto" / cc.PROTO_FILES[0]
    target.parent.mkdir(parents=True)
    target.write_text(src.replace(old, new))
    out = tmp_path / "current.binpb"
    out.write_bytes(cc.compile_protos("protoc", root=tmp_path / "proto").SerializeToString())
    return out


def test_cli_fails_on_a_retyped_field_compiled_by_protoc(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    current = edited_proto(tmp_path, "uint64 steps_shaped = 7;", "uint32 steps_shaped = 7;")
    assert cc.main(["--current", str(current)]) == 1
    out = capsys.readouterr().out
    assert "field tamrm.v1.TaskStats.steps_shaped = 7 changed type from uint64 to uint32" in out, (
        out
    )


def test_cli_passes_an_added_field_and_rpc_compiled_by_protoc(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    current = edited_proto(
        tmp_path,
        "  uint32 open_streams = 8;\n",
        "  uint32 open_streams = 8;\n  repeated string labels = 9;\n",
    )
    assert cc.main(["--current", str(current)]) == 0, capsys.readouterr().out


def test_write_records_a_new_baseline_once_and_refuses_a_breaking_proto(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dir_ = tmp_path / "compat"
    dir_.mkdir()
    assert cc.main(["--baseline-dir", str(dir_)]) == 2  # no baseline: not a silent pass
    assert cc.main(["--baseline-dir", str(dir_), "--write", "9.0"]) == 0
    written = dir_ / "tamrm.v1.9.0.binpb"
    current = cc.compile_protos("protoc")
    assert cc.breaking_changes(cc.load(written), current) == []
    assert cc.breaking_changes(current, cc.load(written)) == []
    assert cc.main(["--baseline-dir", str(dir_), "--write", "9.0"]) == 2  # never rewritten
    broken = edited_proto(tmp_path, "uint64 steps_shaped = 7;", "uint64 steps_done = 7;")
    args = ["--baseline-dir", str(dir_), "--current", str(broken)]
    assert cc.main([*args, "--write", "9.1"]) == 1
    assert not (dir_ / "tamrm.v1.9.1.binpb").exists()
    capsys.readouterr()
    assert cc.main(args) == 1
    assert "steps_shaped = 7 was renamed to steps_done" in capsys.readouterr().out


def test_the_newest_baseline_records_the_current_proto() -> None:
    """A change of proto/ lands with its baseline, so the next change is checked against it."""
    unrecorded = cc.breaking_changes(cc.compile_protos("protoc"), BASE)
    assert unrecorded == [], (
        "proto/ has additions the newest baseline does not record; record them with "
        "`python proto/compat/check_compat.py --write <next version>` (docs/languages.md): "
        + "; ".join(unrecorded)
    )


def test_baselines_are_ordered_by_version_not_by_name(tmp_path: Path) -> None:
    for v in ("1.10", "1.2", "1.9"):
        (tmp_path / f"tamrm.v1.{v}.binpb").write_bytes(b"")
    assert [p.name for p in cc.baselines(tmp_path)] == [
        "tamrm.v1.1.2.binpb",
        "tamrm.v1.1.9.binpb",
        "tamrm.v1.1.10.binpb",
    ]
