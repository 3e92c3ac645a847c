"""The pool export format read and written without a server (docs/storage.md, "Pool export
format"): the committed fixtures (which the server's ``tamrm pool import`` reads too) and
every refusal, each naming its line."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import tamrm
from tamrm import _pool_file as pf

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "pool"
CASES = json.loads((FIXTURES / "cases.json").read_text(encoding="utf-8"))


def bits64(x: float) -> str:
    return f"0x{struct.unpack('<Q', struct.pack('<d', x))[0]:016x}"


def test_the_manifest_lists_every_fixture() -> None:
    files = {p.name for p in FIXTURES.glob("*.jsonl")}
    listed = set(CASES["valid"]) | set(CASES["refused"])
    assert files == listed
    assert len(CASES["valid"]) >= 2 and len(CASES["refused"]) >= 10


@pytest.mark.parametrize("name", sorted(CASES["valid"]))
def test_a_valid_fixture_reads_as_the_manifest_says(name: str) -> None:
    want = CASES["valid"][name]
    got = pf.read_pool_file(FIXTURES / name)
    assert got.task_id == want["task_id"]
    assert got.config == want["config"]
    assert got.pool_version == want["pool_version"]
    assert [t.seq for t in got.trajectories] == [t["seq"] for t in want["trajectories"]]
    assert [bits64(t.score) for t in got.trajectories] == [
        t["score_bits"] for t in want["trajectories"]
    ]
    for t, w in zip(got.trajectories, want["trajectories"], strict=True):
        if "actions" in w:
            assert t.actions.dtype == np.int64 and t.actions.tolist() == w["actions"]
        else:
            assert t.actions.dtype == np.float32
            assert t.actions.view(np.uint32).tolist() == w["action_bits"]


@pytest.mark.parametrize("name", sorted(CASES["refused"]))
def test_a_refused_fixture_names_its_line(name: str) -> None:
    line = CASES["refused"][name]["line"]
    with pytest.raises(tamrm.PoolFileError) as info:
        pf.read_pool_file(FIXTURES / name)
    assert info.value.line == line
    assert f"{FIXTURES / name}, line {line}: " in str(info.value)


# -- every rule, one file each ------------------------------------------------------------

CONFIG: dict[str, Any] = {
    "num_actions": 3,
    "action_dim": 0,
    "pool_capacity": 2,
    "k": 2,
    "start_step": 0,
    "min_pool_size": 1,
    "alpha": 0.8,
    "beta": 0.8,
    "gamma": 0.99,
    "max_trajectory_len": 4,
    "gate_potential": False,
    "require_score_spread": False,
}


def header(n: int = 1, config: dict[str, Any] | None = None, **changes: Any) -> dict[str, Any]:
    h = {
        "format": "tamrm-pool",
        "version": 1,
        "task_id": "t",
        "config": CONFIG if config is None else config,
        "pool_version": 1,
        "trajectories": n,
    }
    h.update(changes)
    return h


def text(*lines: Any) -> str:
    return "".join((x if isinstance(x, str) else json.dumps(x)) + "\n" for x in lines)


TRAJ = {"seq": 1, "score": 1.0, "actions": [0, 2]}
CONT = {**CONFIG, "num_actions": 0, "action_dim": 2}

# (file text, line at fault, a fragment of the message)
REFUSED: dict[str, tuple[str | bytes, int, str]] = {
    "empty file": ("", 1, "empty"),
    "header not an object": ("[1]\n", 1, "expected an object"),
    "header not JSON": ('{"format": tamrm}\n', 1, "not JSON"),
    "header cut short": ('{"format": "tamrm-pool", "vers', 1, "cut short"),
    "no format": (text({k: v for k, v in header().items() if k != "format"}, TRAJ), 1, "format"),
    "another format": (text(header(format="other"), TRAJ), 1, 'format "other"'),
    "version 2": (text(header(version=2), TRAJ), 1, "version 2 is not supported"),
    "version as a string": (text(header(version="1"), TRAJ), 1, 'version "1"'),
    "version 1.0": (text(header(version=1.0), TRAJ), 1, "version 1.0"),
    "no version": (text({k: v for k, v in header().items() if k != "version"}), 1, "version"),
    "unknown header key": (text(header(comment="x"), TRAJ), 1, "'comment'"),
    "missing header key": (
        text({k: v for k, v in header().items() if k != "pool_version"}),
        1,
        "'pool_version'",
    ),
    "duplicate key": (
        '{"format": "tamrm-pool", "format": "tamrm-pool"}\n',
        1,
        "'format' appears twice",
    ),
    "bad task id": (text(header(task_id="a b"), TRAJ), 1, "task_id"),
    "empty task id": (text(header(task_id=""), TRAJ), 1, "task_id"),
    "task id too long": (text(header(task_id="a" * 129), TRAJ), 1, "task_id"),
    "negative pool_version": (text(header(pool_version=-1), TRAJ), 1, "pool_version"),
    "count as a float": (text(header(n=1.0), TRAJ), 1, "trajectories: must be an integer"),
    "count past capacity": (text(header(n=3)), 1, "more than the pool_capacity 2"),
    "config not an object": (text(header(config=[1])), 1, "config: must be an object"),
    "config field unknown": (text(header(config={**CONFIG, "delta": 1})), 1, "config.delta"),
    "config field missing": (
        text(header(config={k: v for k, v in CONFIG.items() if k != "k"})),
        1,
        "config.k: missing",
    ),
    "config int as a float": (text(header(config={**CONFIG, "k": 2.0})), 1, "config.k"),
    "config int as a bool": (text(header(config={**CONFIG, "k": True})), 1, "config.k"),
    "config int past uint32": (
        text(header(config={**CONFIG, "start_step": 2**32})),
        1,
        "config.start_step",
    ),
    "config bool as an int": (
        text(header(config={**CONFIG, "gate_potential": 1})),
        1,
        "config.gate_potential",
    ),
    "config float as a string": (text(header(config={**CONFIG, "alpha": "1"})), 1, "alpha"),
    "both action kinds": (text(header(config={**CONFIG, "action_dim": 2})), 1, "both are set"),
    "no action kind": (text(header(config={**CONFIG, "num_actions": 0})), 1, "both are 0"),
    "capacity 0": (
        text(header(n=0, config={**CONFIG, "pool_capacity": 0})),
        1,
        "config.pool_capacity",
    ),
    "k 0": (text(header(config={**CONFIG, "k": 0})), 1, "config.k"),
    "min_pool_size past capacity": (
        text(header(config={**CONFIG, "min_pool_size": 3})),
        1,
        "config.min_pool_size",
    ),
    "gamma past 1": (text(header(config={**CONFIG, "gamma": 1.5})), 1, "config.gamma"),
    "alpha NaN": (
        text(header()).replace('"alpha": 0.8', '"alpha": NaN'),
        1,
        "config.alpha: must be finite",
    ),
    "beta infinite": (
        text(header()).replace('"beta": 0.8', '"beta": 1e999'),
        1,
        "config.beta: must be finite",
    ),
    "max_trajectory_len 0": (
        text(header(config={**CONFIG, "max_trajectory_len": 0})),
        1,
        "config.max_trajectory_len",
    ),
    "not UTF-8": (
        text(header()).encode() + b'{"seq": 1, "score": 1.0, "a\xff": [0]}\n',
        2,
        "UTF-8",
    ),
    "an empty line": (text(header(n=2), TRAJ) + "\n" + json.dumps(TRAJ) + "\n", 3, "empty line"),
    "a trajectory not an object": (text(header(), [0, 1]), 2, "expected an object"),
    "a trajectory line not JSON": (text(header(), "{seq: 1}"), 2, "not JSON"),
    "a trajectory line cut, then more": (
        text(header(n=2), '{"seq": 1, "score": 1.0, "actions": [0', TRAJ),
        2,
        "ends before its JSON object does",
    ),
    "unknown trajectory key": (text(header(), {**TRAJ, "length": 2}), 2, "'length'"),
    "missing trajectory key": (text(header(), {"seq": 1, "actions": [0]}), 2, "'score'"),
    "seq negative": (text(header(), {**TRAJ, "seq": -1}), 2, "seq"),
    "seq as a float": (text(header(), {**TRAJ, "seq": 1.5}), 2, "seq"),
    "seq repeated": (text(header(n=2), TRAJ, TRAJ), 3, "seq: 1, not above"),
    "seq going down": (text(header(n=2), {**TRAJ, "seq": 5}, TRAJ), 3, "seq: 1, not above"),
    "score as a string": (text(header(), {**TRAJ, "score": "1"}), 2, "score"),
    "score infinite": (
        text(header()) + '{"seq": 1, "score": -Infinity, "actions": [0]}\n',
        2,
        "score",
    ),
    "score past the doubles, as an integer": (
        text(header(), {**TRAJ, "score": 10**400}),
        2,
        "score: must be finite",
    ),
    "actions not a list": (text(header(), {**TRAJ, "actions": 1}), 2, "actions: must be a list"),
    "actions empty": (text(header(), {**TRAJ, "actions": []}), 2, "actions: empty"),
    "actions too long": (text(header(), {**TRAJ, "actions": [0] * 5}), 2, "max_trajectory_len 4"),
    "action negative": (text(header(), {**TRAJ, "actions": [0, -1]}), 2, "actions[1]"),
    "action a bool": (text(header(), {**TRAJ, "actions": [True]}), 2, "actions[0]"),
    "action a vector in a discrete task": (
        text(header(), {**TRAJ, "actions": [[0.5]]}),
        2,
        "actions[0]",
    ),
    "vector not a list": (
        text(header(config=CONT), {**TRAJ, "actions": [1.0, 2.0]}),
        2,
        "actions[0]: must be a list of 2 numbers",
    ),
    "vector too long": (
        text(header(config=CONT), {**TRAJ, "actions": [[1.0, 2.0, 3.0]]}),
        2,
        "has 3 values, expected action_dim 2",
    ),
    "vector value a string": (
        text(header(config=CONT), {**TRAJ, "actions": [[1.0, "2"]]}),
        2,
        "actions[0][1]",
    ),
    "vector value a bool": (
        text(header(config=CONT), {**TRAJ, "actions": [[1.0, False]]}),
        2,
        "actions[0][1]",
    ),
    "vector value NaN": (
        text(header(config=CONT)) + '{"seq": 1, "score": 1.0, "actions": [[1.0, NaN]]}\n',
        2,
        "actions[0][1]: must be a finite float32",
    ),
    "vector value past float32": (
        text(header(config=CONT), {**TRAJ, "actions": [[1.0, 2], [-3.5e38, 0.0]]}),
        2,
        "actions[1][0]",
    ),
    "vector value past the doubles, as an integer": (
        text(header(config=CONT), {**TRAJ, "actions": [[10**400, 0.0]]}),
        2,
        "actions[0][0]",
    ),
    "more lines than announced": (text(header(), TRAJ, {**TRAJ, "seq": 2}), 3, "more"),
    "fewer lines than announced": (text(header(n=2), TRAJ), 3, "ends after 1 of the 2"),
    "none of the announced lines": (text(header(n=2)), 2, "ends after 0 of the 2"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_every_rule_refuses_with_the_line(case: str) -> None:
    data, line, fragment = REFUSED[case]
    file: Any = io.BytesIO(data) if isinstance(data, bytes) else io.StringIO(data)
    with pytest.raises(tamrm.PoolFileError) as info:
        pf.read_pool_file(file)
    assert info.value.line == line, str(info.value)
    assert f"line {line}: " in str(info.value)
    assert fragment in info.value.problem, str(info.value)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    "variant",
    ["as written", "no final newline", "CRLF", "bytes", "keys in another order", "compact"],
)
def test_what_a_reader_accepts(variant: str) -> None:
    lines = [header(n=2, config=CONT), {**TRAJ, "actions": [[0.1, 2]]}, {**TRAJ, "seq": 9}]
    lines[2]["actions"] = [[-0.0, 1e-45], [3, 4.5]]
    data: str | bytes = text(*lines)
    if variant == "no final newline":
        data = data[:-1]
    elif variant == "CRLF":
        data = data.replace("\n", "\r\n")
    elif variant == "bytes":
        data = data.encode()
    elif variant == "keys in another order":
        data = text(*(dict(reversed(x.items())) for x in lines))
    elif variant == "compact":
        data = "".join(json.dumps(x, separators=(",", ":")) + "\n" for x in lines)
    got = pf.read_pool_file(io.BytesIO(data) if isinstance(data, bytes) else io.StringIO(data))
    assert got.config == CONT
    assert [t.seq for t in got.trajectories] == [1, 9]
    # A number is read as a double, then rounded to the nearest float32.
    first, second = (t.actions for t in got.trajectories)
    assert first.dtype == np.float32 and first.tolist() == [[float(np.float32(0.1)), 2.0]]
    assert second.view(np.uint32).tolist() == [
        [0x80000000, 1],  # -0.0 and the smallest subnormal float32
        [int(np.float32(3).view(np.uint32)), int(np.float32(4.5).view(np.uint32))],
    ]


def test_a_pool_of_no_trajectories_is_one_line() -> None:
    got = pf.read_pool_file(io.StringIO(text(header(n=0))))
    assert got.trajectories == [] and got.task_id == "t"


def test_the_header_is_checked_for_its_format_and_version_before_its_keys() -> None:
    # A later version may add or drop keys: the refusal names the version, not a key.
    later = {"format": "tamrm-pool", "version": 2, "pool": {}}
    with pytest.raises(tamrm.PoolFileError, match="version 2 is not supported"):
        pf.read_pool_file(io.StringIO(text(later)))


def test_the_format_knows_every_config_field() -> None:
    # A field added to TaskConfig must be added here as optional in version-1 files (its
    # default when missing; docs/storage.md), not required.
    assert pf.V1_CONFIG_FIELDS == tamrm.CONFIG_FIELDS


# -- writing ------------------------------------------------------------------------------


def sample(discrete: bool) -> tuple[tamrm.Task, tamrm.Pool]:
    config = tamrm.TaskConfig(**{**(CONFIG if discrete else CONT), "pool_capacity": 3})
    stats = tamrm.TaskStats(2, 5, 1, 0.0, 0.0, 0, 0, 0)
    if discrete:
        actions: list[Any] = [np.array([0, 2, 1]), np.array([1])]
    else:
        actions = [np.array([[0.1, -2.5]], np.float32), np.array([[1e-7, 3e38]] * 2, np.float32)]
    trajectories = [
        tamrm.Trajectory(actions=actions[0], score=0.1 + 0.2, seq=2),
        tamrm.Trajectory(actions=actions[1], score=-1e-300, seq=5),
    ]
    return tamrm.Task("w/x", config, stats), tamrm.Pool("w/x", 5, trajectories)


@pytest.mark.parametrize("discrete", [True, False])
def test_what_is_written_reads_back_bit_for_bit(discrete: bool) -> None:
    task, pool = sample(discrete)
    out = io.StringIO()
    assert pf.write_pool_file(out, task, pool) == 2
    assert not out.closed
    written = out.getvalue()
    assert written.endswith("\n") and written.count("\n") == 3
    head = json.loads(written.splitlines()[0])
    assert list(head) == list(pf.HEADER_KEYS)
    assert list(head["config"]) == list(tamrm.CONFIG_FIELDS)
    assert [list(json.loads(x)) for x in written.splitlines()[1:]] == [list(pf.TRAJECTORY_KEYS)] * 2
    got = pf.read_pool_file(io.StringIO(written))
    assert (got.task_id, got.pool_version) == ("w/x", 5)
    assert got.config == {f: getattr(task.config, f) for f in tamrm.CONFIG_FIELDS}
    for g, t in zip(got.trajectories, pool.trajectories, strict=True):
        assert g.seq == t.seq and bits64(g.score) == bits64(t.score)
        assert g.actions.dtype == t.actions.dtype
        assert g.actions.tobytes() == t.actions.astype(g.actions.dtype).tobytes()


def test_a_path_is_written_whole_or_not_at_all(tmp_path: Path) -> None:
    task, pool = sample(True)
    path = tmp_path / "pool.jsonl"
    path.write_text("old", encoding="utf-8")

    class Unwritable:
        def tolist(self) -> list[int]:
            raise RuntimeError("disk full")

    broken = tamrm.Pool("w/x", 5, [*pool.trajectories, tamrm.Trajectory(Unwritable(), 1.0, 9)])  # type: ignore[arg-type]
    with pytest.raises(RuntimeError):
        pf.write_pool_file(path, task, broken)
    assert path.read_text(encoding="utf-8") == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pool.jsonl"]  # no temporary left
    assert pf.write_pool_file(str(path), task, pool) == 2
    assert pf.read_pool_file(path).pool_version == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pool.jsonl"]
