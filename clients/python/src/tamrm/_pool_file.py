"""The pool export format, ``tamrm-pool`` version 1: written and read (and checked) here.

JSON Lines in UTF-8: a header line (the task's id and resolved config, the pool's version
and how many trajectories follow), then one line per stored trajectory in ``seq`` order.
docs/storage.md ("Pool export format") is the format's definition, for this module and for
the server's ``tamrm pool export/import``; ``clients/python/tests/fixtures/pool/`` holds files
both read. :func:`read_pool_file` checks a whole file before its caller makes any call, and
refuses one with a :class:`PoolFileError` naming the line.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from tamrm._types import CONFIG_FIELDS, Pool, Task

__all__ = [
    "FORMAT",
    "HEADER_KEYS",
    "TRAJECTORY_KEYS",
    "V1_CONFIG_FIELDS",
    "VERSION",
    "PoolFile",
    "PoolFileError",
    "PoolFileLike",
    "PoolRecord",
    "config_differences",
    "read_pool_file",
    "write_pool_file",
]

#: The header's ``format``.
FORMAT = "tamrm-pool"
#: The one version of the format this module writes and reads.
VERSION = 1
#: The header's keys, in the order they are written.
HEADER_KEYS = ("format", "version", "task_id", "config", "pool_version", "trajectories")
#: A trajectory line's keys, in the order they are written.
TRAJECTORY_KEYS = ("seq", "score", "actions")
#: The ``TaskConfig`` fields a version-1 header holds, every one required: the first twelve,
#: in proto order (fields are only ever appended). A field added to ``TaskConfig`` later
#: is optional in a version-1 file (its default when missing).
V1_CONFIG_FIELDS = CONFIG_FIELDS[:12]
_UINT_FIELDS = frozenset(
    {"num_actions", "action_dim", "pool_capacity", "k", "start_step", "min_pool_size"}
    | {"max_trajectory_len"}
)
_BOOL_FIELDS = frozenset({"gate_potential", "require_score_spread"})
_UINT32_MAX = 2**32 - 1
_UINT64_MAX = 2**64 - 1
_TASK_ID = re.compile(r"[A-Za-z0-9._:/-]{1,128}\Z")

#: Where a pool file is: a path, or an open file object (text; bytes are read as UTF-8).
PoolFileLike = str | os.PathLike[str] | IO[str]


class PoolFileError(ValueError):
    """A pool file refused on import: what is wrong, and on which line.

    Nothing was imported: the whole file is checked before the first call.

    Attributes:
        line: The line at fault, counted from 1 (the header is line 1).
        source: The file's path, or a description of the file object.
        problem: What is wrong with that line.
    """

    def __init__(self, source: str, line: int, problem: str) -> None:
        super().__init__(f"{source}, line {line}: {problem}")
        self.source = source
        self.line = line
        self.problem = problem


@dataclass(frozen=True)
class PoolRecord:
    """One trajectory line: ``actions`` ``int64 (L,)`` or ``float32 (L, action_dim)``."""

    seq: int
    score: float
    actions: npt.NDArray[np.int64] | npt.NDArray[np.float32]


@dataclass(frozen=True)
class PoolFile:
    """A checked pool file: its header's values and its trajectories, in ``seq`` order.

    ``config`` maps every ``TaskConfig`` field to its value (a complete, valid config).
    """

    task_id: str
    config: dict[str, Any]
    pool_version: int
    trajectories: list[PoolRecord]


# -- writing -------------------------------------------------------------------------------


def _line(value: dict[str, Any]) -> str:
    # float repr is the shortest text that reads back to the same double; a float32 action
    # widened to a double is exact, so it reads back to the same float32.
    return json.dumps(value, allow_nan=False) + "\n"


def pool_lines(task: Task, pool: Pool) -> Iterator[str]:
    """The lines of the export of ``pool``, the pool of ``task``."""
    config = {name: getattr(task.config, name) for name in V1_CONFIG_FIELDS}
    yield _line(
        {
            "format": FORMAT,
            "version": VERSION,
            "task_id": task.task_id,
            "config": config,
            "pool_version": pool.pool_version,
            "trajectories": len(pool.trajectories),
        }
    )
    for t in pool.trajectories:
        yield _line({"seq": t.seq, "score": t.score, "actions": t.actions.tolist()})


def write_pool_file(file: PoolFileLike, task: Task, pool: Pool) -> int:
    """Write the export of ``pool`` (of ``task``) to ``file``; return its trajectory count.

    A path is written whole or not at all (a temporary file beside it, then renamed over
    it); a file object is written to and left open.
    """
    if isinstance(file, (str, os.PathLike)):
        path = Path(file)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as out:
                out.writelines(pool_lines(task, pool))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    else:
        file.writelines(pool_lines(task, pool))
    return len(pool.trajectories)


# -- reading -------------------------------------------------------------------------------


class _Refused(Exception):
    """A line's problem, before the reader adds the file and the line number."""


def _lines(file: PoolFileLike) -> tuple[str, list[str | bytes]]:
    """The file's name for messages, and its lines without their line feeds."""
    if isinstance(file, (str, os.PathLike)):
        source = os.fspath(file)
        data: str | bytes = Path(file).read_bytes()
    else:
        source = str(getattr(file, "name", None) or f"<{type(file).__name__}>")
        data = file.read()
    parts: list[str | bytes]
    if isinstance(data, bytes):
        parts = list(data.split(b"\n"))
        ends_with_newline = data.endswith(b"\n")
    else:
        parts = list(data.split("\n"))
        ends_with_newline = data.endswith("\n")
    if ends_with_newline:
        parts.pop()  # the last line's terminator, not an empty line after it
    return source, parts


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Refused(f"the key {key!r} appears twice in one object")
        out[key] = value
    return out


def _unclosed(text: str) -> bool:
    """Whether ``text`` ends inside a string, an object or an array (a line cut short)."""
    depth, in_string, escaped = 0, False, False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
    return in_string or depth > 0


def _parse(raw: str | bytes, last: bool) -> dict[str, Any]:
    """One line as a JSON object."""
    if isinstance(raw, bytes):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise _Refused(f"not UTF-8 (byte {exc.start + 1} of the line)") from None
    else:
        text = raw
    if not text.strip():
        raise _Refused("an empty line (every line is one JSON object)")
    try:
        value = json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as exc:
        if _unclosed(text):
            cut = ": the file is cut short" if last else ""
            raise _Refused(f"the line ends before its JSON object does{cut}") from None
        raise _Refused(f"not JSON: {exc.msg} at column {exc.colno}") from None
    if not isinstance(value, dict):
        raise _Refused(f"a JSON {type(value).__name__}, expected an object")
    return value


def _show(value: Any) -> str:
    """A JSON value for a message, cut to 40 characters."""
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _keys(obj: dict[str, Any], expected: tuple[str, ...], what: str) -> None:
    missing = [k for k in expected if k not in obj]
    if missing:
        raise _Refused(f"{what} lacks {', '.join(map(repr, missing))}")
    unknown = [k for k in obj if k not in expected]
    if unknown:
        raise _Refused(f"{what} has an unknown key {unknown[0]!r}")


def _uint(value: Any, name: str, most: int) -> int:
    """A JSON integer (no fraction, no exponent) in ``0..most``."""
    if type(value) is not int:
        raise _Refused(f"{name}: must be an integer, got {_show(value)}")
    if not 0 <= value <= most:
        raise _Refused(f"{name}: must be in 0..={most}, got {value}")
    return value


def _real(value: Any, name: str) -> float:
    """A JSON number as a double (finiteness is the caller's to check)."""
    if type(value) is float:
        return value
    if type(value) is int:
        try:
            return float(value)
        except OverflowError:
            return math.inf if value > 0 else -math.inf
    raise _Refused(f"{name}: must be a number, got {_show(value)}")


def _config(value: Any) -> dict[str, Any]:
    """The header's config, checked against every range of SPEC §1.1."""
    if not isinstance(value, dict):
        raise _Refused(f"config: must be an object, got {_show(value)}")
    for name in value:
        if name not in V1_CONFIG_FIELDS:
            raise _Refused(
                f"config.{name}: an unknown TaskConfig field (a file of a newer server?)"
            )
    out: dict[str, Any] = {}
    for name in V1_CONFIG_FIELDS:
        if name not in value:
            raise _Refused(f"config.{name}: missing (the config holds every TaskConfig field)")
        v = value[name]
        if name in _UINT_FIELDS:
            out[name] = _uint(v, f"config.{name}", _UINT32_MAX)
        elif name in _BOOL_FIELDS:
            if type(v) is not bool:
                raise _Refused(f"config.{name}: must be true or false, got {_show(v)}")
            out[name] = v
        else:
            out[name] = _real(v, f"config.{name}")
    _check_ranges(out)
    return out


def _check_ranges(c: dict[str, Any]) -> None:
    """SPEC §1.1's ranges, as the server's ``TaskConfig::resolve`` checks them."""
    if (c["num_actions"] == 0) == (c["action_dim"] == 0):
        both = "both are 0" if c["num_actions"] == 0 else "both are set"
        raise _Refused(f"config: exactly one of num_actions and action_dim is non-zero ({both})")
    capacity = c["pool_capacity"]
    if capacity < 1:
        raise _Refused("config.pool_capacity: must be >= 1, got 0")
    for name in ("k", "min_pool_size"):
        if not 1 <= c[name] <= capacity:
            raise _Refused(
                f"config.{name}: must be in 1..={capacity} (pool_capacity), got {c[name]}"
            )
    for name in ("alpha", "beta"):
        if not math.isfinite(c[name]):
            raise _Refused(f"config.{name}: must be finite, got {c[name]}")
    if not 0.0 <= c["gamma"] <= 1.0:
        raise _Refused(f"config.gamma: must be in [0, 1], got {c['gamma']}")
    if c["max_trajectory_len"] < 1:
        raise _Refused("config.max_trajectory_len: must be >= 1, got 0")


def _header(obj: dict[str, Any]) -> tuple[str, dict[str, Any], int, int]:
    """The header's task id, config, pool version and trajectory count."""
    if obj.get("format") != FORMAT:
        found = _show(obj["format"]) if "format" in obj else "missing"
        raise _Refused(f"not a tamrm pool export (format {found}, expected {FORMAT!r})")
    version = obj.get("version", VERSION)
    if type(version) is not int or version != VERSION:
        raise _Refused(
            f"format version {_show(version)} is not supported (this reader reads version "
            f"{VERSION})"
        )
    _keys(obj, HEADER_KEYS, "the header")
    task_id = obj["task_id"]
    if not isinstance(task_id, str) or not _TASK_ID.match(task_id):
        raise _Refused(
            f"task_id: must be 1-128 characters of [A-Za-z0-9._:/-], got {_show(task_id)}"
        )
    config = _config(obj["config"])
    pool_version = _uint(obj["pool_version"], "pool_version", _UINT64_MAX)
    count = _uint(obj["trajectories"], "trajectories", _UINT32_MAX)
    if count > config["pool_capacity"]:
        raise _Refused(
            f"trajectories: {count}, more than the pool_capacity {config['pool_capacity']}"
        )
    return task_id, config, pool_version, count


def _discrete(actions: list[Any], num_actions: int) -> npt.NDArray[np.int64]:
    for i, a in enumerate(actions):
        if type(a) is not int:
            raise _Refused(f"actions[{i}]: must be an integer action, got {_show(a)}")
        if not 0 <= a < num_actions:
            raise _Refused(f"actions[{i}]: action {a} out of range for num_actions {num_actions}")
    return np.array(actions, dtype=np.int64)


def _continuous(actions: list[Any], dim: int) -> npt.NDArray[np.float32]:
    for i, row in enumerate(actions):
        if type(row) is not list:
            raise _Refused(f"actions[{i}]: must be a list of {dim} numbers, got {_show(row)}")
        if len(row) != dim:
            raise _Refused(f"actions[{i}]: has {len(row)} values, expected action_dim {dim}")
        for j, v in enumerate(row):
            if type(v) is not float and type(v) is not int:
                raise _Refused(f"actions[{i}][{j}]: must be a number, got {_show(v)}")
    try:
        rows = np.array(actions, dtype=np.float64)
    except OverflowError:  # an integer past the doubles' range: infinite, refused below
        rows = np.array([[_real(v, "") for v in row] for row in actions], dtype=np.float64)
    with np.errstate(over="ignore"):
        out = rows.astype(np.float32)  # to the nearest float32, ties to even
    bad = np.argwhere(~np.isfinite(out))
    if len(bad):
        i, j = (int(x) for x in bad[0])
        raise _Refused(f"actions[{i}][{j}]: must be a finite float32, got {float(rows[i, j])!r}")
    return out


def _trajectory(obj: dict[str, Any], config: dict[str, Any], after: int | None) -> PoolRecord:
    _keys(obj, TRAJECTORY_KEYS, "a trajectory line")
    seq = _uint(obj["seq"], "seq", _UINT64_MAX)
    if after is not None and seq <= after:
        raise _Refused(f"seq: {seq}, not above the previous line's {after} (seqs increase)")
    score = _real(obj["score"], "score")
    if not math.isfinite(score):
        raise _Refused(f"score: must be finite, got {score}")
    actions = obj["actions"]
    if not isinstance(actions, list):
        raise _Refused(f"actions: must be a list, got {_show(actions)}")
    if not actions:
        raise _Refused("actions: empty (a stored trajectory has at least one action)")
    if len(actions) > config["max_trajectory_len"]:
        raise _Refused(
            f"actions: {len(actions)} actions, more than max_trajectory_len "
            f"{config['max_trajectory_len']}"
        )
    if config["num_actions"] > 0:
        array: npt.NDArray[Any] = _discrete(actions, config["num_actions"])
    else:
        array = _continuous(actions, config["action_dim"])
    return PoolRecord(seq=seq, score=score, actions=array)


def read_pool_file(file: PoolFileLike) -> PoolFile:
    """Read and check a whole pool file.

    Raises:
        PoolFileError: The first thing wrong, with its line: a file cut short, more lines
            than the header announces, another format or version, a config SPEC rejects,
            actions out of range, of the wrong dimension, empty or non-finite, a
            non-finite score, seqs that do not strictly increase, more trajectories than
            ``pool_capacity`` (docs/storage.md lists every rule).
        OSError: The file cannot be read.
    """
    source, lines = _lines(file)
    line = 1
    try:
        if not lines:
            raise _Refused("the file is empty (a pool file starts with its header)")
        task_id, config, pool_version, count = _header(_parse(lines[0], len(lines) == 1))
        records: list[PoolRecord] = []
        for line, raw in enumerate(lines[1:], start=2):
            if len(records) == count:
                raise _Refused(f"more trajectory lines than the {count} the header announces")
            obj = _parse(raw, line == len(lines))
            after = records[-1].seq if records else None
            records.append(_trajectory(obj, config, after))
        if len(records) < count:
            line = len(lines) + 1
            raise _Refused(
                f"the file ends after {len(records)} of the {count} trajectories the header "
                "announces: it is cut short"
            )
    except _Refused as exc:
        raise PoolFileError(source, line, str(exc)) from None
    return PoolFile(task_id=task_id, config=config, pool_version=pool_version, trajectories=records)


def config_differences(config: dict[str, Any], existing: Any) -> list[str]:
    """Each field in which the file's ``config`` and a task's ``TaskConfig`` differ.

    As ``name: task X, file Y``; floats are compared bit for bit, as ``CreateTask`` does.
    """
    out = []
    for name in V1_CONFIG_FIELDS:
        mine, theirs = config[name], getattr(existing, name)
        same = (
            mine.hex() == float(theirs).hex()
            if isinstance(mine, float)
            else (mine == theirs and type(mine) is type(theirs))
        )
        if not same:
            out.append(f"{name}: task {theirs}, file {mine}")
    return out
