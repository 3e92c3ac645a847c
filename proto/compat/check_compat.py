"""Proto breaking-change check: the current proto/ against every committed baseline.

A baseline is the descriptor set of a released API version, committed as
``proto/compat/tamrm.v1.<version>.binpb``. The current proto may only add: every message,
field, enum value, service and RPC of a baseline must still be there, with the same
number, name, type, label, presence and oneof, and every RPC with the same request and
response types and streaming. docs/languages.md, "Changing the proto", has the rule.

Usage::

    python proto/compat/check_compat.py              # check; exit 1 naming each break
    python proto/compat/check_compat.py --write 1.3  # add the baseline of a new release

The current descriptor set is compiled with ``protoc`` (``--protoc``; Debian's
protobuf-compiler).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from google.protobuf import descriptor_pb2 as pb

HERE = Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent
PROTO_FILES = ("tamrm/v1/shaping.proto",)
BASELINE_PREFIX = "tamrm.v1."

# File options whose change renames or moves every generated symbol of some language.
CODEGEN_OPTIONS = (
    "java_package",
    "java_outer_classname",
    "java_multiple_files",
    "go_package",
    "csharp_namespace",
    "objc_class_prefix",
    "php_namespace",
    "ruby_package",
    "swift_prefix",
)

Label = pb.FieldDescriptorProto.Label
Span = tuple[int, int]
T = TypeVar("T")
Type = pb.FieldDescriptorProto.Type


@dataclass(frozen=True)
class Message:
    """A message type with its fully qualified name and the file that declares it."""

    name: str
    file: str
    proto: pb.DescriptorProto


@dataclass(frozen=True)
class Enum:
    """An enum type with its fully qualified name and the file that declares it."""

    name: str
    file: str
    proto: pb.EnumDescriptorProto


@dataclass(frozen=True)
class Index:
    """Every message, enum and service of a descriptor set by fully qualified name."""

    files: dict[str, pb.FileDescriptorProto]
    messages: dict[str, Message]
    enums: dict[str, Enum]
    services: dict[str, pb.ServiceDescriptorProto]


def _qualify(scope: str, name: str) -> str:
    return f"{scope}.{name}" if scope else name


def _walk(
    file: str, scope: str, messages: Iterable[pb.DescriptorProto]
) -> Iterator[tuple[str, pb.DescriptorProto]]:
    for m in messages:
        name = _qualify(scope, m.name)
        yield name, m
        yield from _walk(file, name, m.nested_type)


def index(fds: pb.FileDescriptorSet) -> Index:
    """Indexes a descriptor set's types (nested ones included) by fully qualified name."""
    idx = Index({}, {}, {}, {})
    for f in fds.file:
        idx.files[f.name] = f
        for e in f.enum_type:
            idx.enums[_qualify(f.package, e.name)] = Enum(_qualify(f.package, e.name), f.name, e)
        for name, m in _walk(f.name, f.package, f.message_type):
            idx.messages[name] = Message(name, f.name, m)
            for e in m.enum_type:
                idx.enums[f"{name}.{e.name}"] = Enum(f"{name}.{e.name}", f.name, e)
        for s in f.service:
            idx.services[_qualify(f.package, s.name)] = s
    return idx


def _type_name(field: pb.FieldDescriptorProto) -> str:
    kind = Type.Name(field.type).removeprefix("TYPE_").lower()
    return f"{kind} {field.type_name.lstrip('.')}" if field.type_name else kind


def _label(field: pb.FieldDescriptorProto) -> str:
    if field.label == Label.LABEL_REPEATED:
        return "repeated"
    if field.label == Label.LABEL_REQUIRED:
        return "required"
    return "optional (explicit presence)" if field.proto3_optional else "singular"


def _oneof(message: pb.DescriptorProto, field: pb.FieldDescriptorProto) -> str | None:
    """The real oneof a field belongs to (None for none, and for proto3 `optional`)."""
    if not field.HasField("oneof_index") or field.proto3_optional:
        return None
    return message.oneof_decl[field.oneof_index].name


def _message_ranges(ranges: Iterable[pb.DescriptorProto.ReservedRange]) -> list[Span]:
    return [(r.start, r.end - 1) for r in ranges]  # a message range's end is exclusive


def _enum_ranges(ranges: Iterable[pb.EnumDescriptorProto.EnumReservedRange]) -> list[Span]:
    return [(r.start, r.end) for r in ranges]  # an enum range's end is inclusive


def _unreserved(old: list[Span], new: list[Span]) -> list[Span]:
    """The parts of the `old` reserved spans that no `new` span covers (inclusive ends)."""
    left: list[Span] = []
    for start, end in old:
        at = start
        for s, e in sorted(new):
            if e < at or s > end:
                continue
            if s > at:
                left.append((at, s - 1))
            at = max(at, e + 1)
            if at > end:
                break
        if at <= end:
            left.append((at, end))
    return left


def _show(spans: list[Span]) -> str:
    return ", ".join(str(s) if s == e else f"{s}-{e}" for s, e in spans)


def _compare_fields(old: Message, new: Message) -> Iterator[str]:
    by_number = {f.number: f for f in new.proto.field}
    by_name = {f.name: f for f in new.proto.field}
    for f in old.proto.field:
        where = f"field {old.name}.{f.name} = {f.number}"
        g = by_number.get(f.number)
        if g is None:
            moved = by_name.get(f.name)
            yield (
                f"{where} was renumbered to {moved.number}"
                if moved is not None
                else f"{where} was removed (its number and name may never be reused)"
            )
            continue
        if g.name != f.name:
            yield f"{where} was renamed to {g.name}"
        if _type_name(g) != _type_name(f):
            yield f"{where} changed type from {_type_name(f)} to {_type_name(g)}"
        if _label(g) != _label(f):
            yield f"{where} changed label from {_label(f)} to {_label(g)}"
        was, now = _oneof(old.proto, f), _oneof(new.proto, g)
        if was != now:
            yield f"{where} moved from oneof {was or '(none)'} to oneof {now or '(none)'}"


def _compare_message(old: Message, new: Message) -> Iterator[str]:
    if new.file != old.file:
        yield f"message {old.name} moved from {old.file} to {new.file}"
    yield from _compare_fields(old, new)
    yield from _reservations(
        f"message {old.name} no longer reserves field",
        (_message_ranges(old.proto.reserved_range), old.proto.reserved_name),
        (_message_ranges(new.proto.reserved_range), new.proto.reserved_name),
    )


def _compare_enum(old: Enum, new: Enum) -> Iterator[str]:
    if new.file != old.file:
        yield f"enum {old.name} moved from {old.file} to {new.file}"
    by_name = {v.name: v for v in new.proto.value}
    for v in old.proto.value:
        g = by_name.get(v.name)
        where = f"enum value {old.name}.{v.name} = {v.number}"
        if g is None:
            yield f"{where} was removed"
        elif g.number != v.number:
            yield f"{where} was renumbered to {g.number}"
    yield from _reservations(
        f"enum {old.name} no longer reserves",
        (_enum_ranges(old.proto.reserved_range), old.proto.reserved_name),
        (_enum_ranges(new.proto.reserved_range), new.proto.reserved_name),
    )


def _reservations(
    prefix: str, old: tuple[list[Span], Iterable[str]], new: tuple[list[Span], Iterable[str]]
) -> Iterator[str]:
    """Reserved numbers and names of `old` that `new` no longer reserves."""
    gone = _unreserved(old[0], new[0])
    if gone:
        yield f"{prefix} numbers {_show(gone)}"
    names = set(old[1]) - set(new[1])
    if names:
        yield f"{prefix} names {sorted(names)}"


def _signature(m: pb.MethodDescriptorProto) -> str:
    req = ("stream " if m.client_streaming else "") + m.input_type.lstrip(".")
    resp = ("stream " if m.server_streaming else "") + m.output_type.lstrip(".")
    return f"({req}) returns ({resp})"


def _compare_service(
    name: str, old: pb.ServiceDescriptorProto, new: pb.ServiceDescriptorProto
) -> Iterator[str]:
    methods = {m.name: m for m in new.method}
    for m in old.method:
        g = methods.get(m.name)
        where = f"rpc {name}.{m.name}"
        if g is None:
            yield f"{where} was removed"
        elif _signature(g) != _signature(m):
            yield f"{where} changed from {_signature(m)} to {_signature(g)}"


def _compare_file(old: pb.FileDescriptorProto, new: pb.FileDescriptorProto) -> Iterator[str]:
    if new.package != old.package:
        yield f"file {old.name} changed package from {old.package} to {new.package}"
    was, now = _codegen_options(old.options), _codegen_options(new.options)
    for option, value in was.items():
        if now.get(option) != value:
            shown = repr(now[option]) if option in now else "(unset)"
            yield f"file {old.name} changed option {option} from {value!r} to {shown}"


def _codegen_options(options: pb.FileOptions) -> dict[str, object]:
    return {fd.name: v for fd, v in options.ListFields() if fd.name in CODEGEN_OPTIONS}


def breaking_changes(baseline: pb.FileDescriptorSet, current: pb.FileDescriptorSet) -> list[str]:
    """Every change from `baseline` to `current` that breaks a client of the baseline.

    Additions (fields, messages, enums and enum values, services, RPCs, reserved numbers)
    are not breaks; anything of the baseline that disappears or changes is, one line each.
    """
    old, new = index(baseline), index(current)
    return [
        *_matched("file", old.files, new.files, lambda _, o, n: _compare_file(o, n)),
        *_matched("message", old.messages, new.messages, lambda _, o, n: _compare_message(o, n)),
        *_matched("enum", old.enums, new.enums, lambda _, o, n: _compare_enum(o, n)),
        *_matched("service", old.services, new.services, _compare_service),
    ]


def _matched(
    kind: str,
    old: dict[str, T],
    new: dict[str, T],
    compare: Callable[[str, T, T], Iterable[str]],
) -> Iterator[str]:
    """Each `old` item missing from `new` is removed; the others are compared by name."""
    for name, item in old.items():
        now = new.get(name)
        if now is None:
            yield f"{kind} {name} was removed"
        else:
            yield from compare(name, item, now)


def compile_protos(
    protoc: str, root: Path = PROTO_ROOT, files: Iterable[str] = PROTO_FILES
) -> pb.FileDescriptorSet:
    """Compiles `files` (relative to `root`) with `protoc` into a descriptor set."""
    exe = shutil.which(protoc)
    if exe is None:
        raise SystemExit(
            f"check_compat: {protoc!r} not found; install protoc "
            "(Debian: apt-get install protobuf-compiler) or pass --protoc PATH"
        )
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "current.binpb"
        cmd = [exe, f"--proto_path={root}", f"--descriptor_set_out={out}", "--include_imports"]
        done = subprocess.run([*cmd, *files], capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SystemExit(f"check_compat: protoc failed:\n{done.stderr.strip()}")
        return load(out)


def load(path: Path) -> pb.FileDescriptorSet:
    """Reads a binary FileDescriptorSet."""
    fds = pb.FileDescriptorSet()
    fds.ParseFromString(path.read_bytes())
    return fds


def baselines(directory: Path = HERE) -> list[Path]:
    """The committed baselines, oldest version first (1.9 before 1.10)."""

    def version(path: Path) -> tuple[int, ...]:
        text = path.name.removeprefix(BASELINE_PREFIX).removesuffix(".binpb")
        return tuple(int(part) for part in text.split(".") if part.isdigit())

    return sorted(directory.glob(f"{BASELINE_PREFIX}*.binpb"), key=version)


def main(argv: list[str] | None = None) -> int:
    """Checks (or with --write records) the current proto against the baselines."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--protoc", default="protoc", help="protoc to compile proto/ with")
    parser.add_argument(
        "--current",
        type=Path,
        help="a descriptor set to check instead of compiling proto/ (for tests and tools)",
    )
    parser.add_argument(
        "--baseline-dir", type=Path, default=HERE, help="where the baselines are (proto/compat)"
    )
    parser.add_argument(
        "--write",
        metavar="VERSION",
        help="record the current proto as the baseline of API version VERSION (e.g. 1.3)",
    )
    args = parser.parse_args(argv)
    current = load(args.current) if args.current else compile_protos(args.protoc)
    files = baselines(args.baseline_dir)

    if args.write:
        target = args.baseline_dir / f"{BASELINE_PREFIX}{args.write}.binpb"
        if target.exists():
            print(f"check_compat: {target} exists; a baseline is never rewritten", file=sys.stderr)
            return 2
        for path in files:
            if breaking_changes(load(path), current):
                print(
                    f"check_compat: the proto breaks {path.name}; fix that first", file=sys.stderr
                )
                return 1
        current.file.sort(key=lambda f: f.name)
        target.write_bytes(current.SerializeToString(deterministic=True))
        print(f"check_compat: wrote {target}")
        return 0

    if not files:
        print(
            f"check_compat: no baseline {BASELINE_PREFIX}*.binpb in {args.baseline_dir}",
            file=sys.stderr,
        )
        return 2
    failed = False
    for path in files:
        breaks = breaking_changes(load(path), current)
        if breaks:
            failed = True
            print(f"check_compat: {len(breaks)} breaking change(s) against {path.name}:")
            for line in breaks:
                print(f"  - {line}")
        else:
            idx = index(load(path))
            fields = sum(len(m.proto.field) for m in idx.messages.values())
            rpcs = sum(len(s.method) for s in idx.services.values())
            print(
                f"check_compat: compatible with {path.name} ({len(idx.messages)} messages, "
                f"{fields} fields, {len(idx.enums)} enums, {rpcs} RPCs)"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
