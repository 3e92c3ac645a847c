"""The committed raw runs: one gzipped JSON record per finished run, added once.

``docs/reproduction/runs/<experiment>/<variant>/<arm>/seedN.json.gz`` holds what ``run``
writes as ``seedN.csv`` and ``seedN.json``: the episodes (the CSV's columns, their pandas
dtypes and rows, as ``pandas.read_csv`` reads them) and the sidecar (``meta``). The gzip
stream has mtime 0 and no file name, so writing an unchanged run again gives the same bytes.
:func:`add_runs` copies the finished runs of a ``run`` directory into the archive: new runs
only, never rewriting a file, and the invocations log's new lines appended.
"""

from __future__ import annotations

import gzip
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

__all__ = [
    "FORMAT",
    "SUFFIX",
    "AddSummary",
    "add_runs",
    "archive_path",
    "decode_run",
    "encode_run",
    "read_csv_run",
    "read_meta",
    "read_record",
]

#: The record's ``format`` field: what a reader of this version understands.
FORMAT = "tamrm-experiments run 1"
#: The name of a run's record: ``seedN`` + this.
SUFFIX = ".json.gz"
#: The runs directory's log of grid invocations (plain JSON lines, appended to).
INVOCATIONS = "invocations.jsonl"


def _plain(value: Any) -> Any:
    """A cell as JSON has it: ``nan`` becomes ``null`` and an infinity ``"inf"`` or
    ``"-inf"`` (restored by the column's dtype)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


def encode_run(meta: dict[str, Any], df: pd.DataFrame) -> bytes:
    """The gzipped record of one run: deterministic bytes for equal inputs."""
    columns = [str(c) for c in df.columns]
    values = [df[c].tolist() for c in df.columns]
    record = {
        "format": FORMAT,
        "meta": meta,
        "columns": columns,
        "dtypes": [str(t) for t in df.dtypes],
        "rows": [[_plain(v) for v in row] for row in zip(*values, strict=True)],
    }
    text = json.dumps(record, separators=(",", ":"), allow_nan=False)
    return gzip.compress(text.encode(), compresslevel=9, mtime=0)


def _record(data: bytes, name: str) -> dict[str, Any]:
    try:
        record = json.loads(gzip.decompress(data))
    except (OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{name}: not a gzipped JSON run record ({exc})") from exc
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        found = record.get("format") if isinstance(record, dict) else type(record).__name__
        raise ValueError(f"{name}: format {found!r}, expected {FORMAT!r}")
    return record


def decode_run(data: bytes, name: str = "record") -> tuple[dict[str, Any], pd.DataFrame]:
    """(sidecar, episodes) of a record written by :func:`encode_run`; ``name`` (its path)
    is named in the ``ValueError`` that a damaged or foreign record raises."""
    record = _record(data, name)
    columns, dtypes, rows = record.get("columns"), record.get("dtypes"), record.get("rows")
    if not isinstance(record.get("meta"), dict) or not isinstance(rows, list):
        raise ValueError(f"{name}: a run record needs a 'meta' object and a 'rows' list")
    if not isinstance(columns, list) or not isinstance(dtypes, list):
        raise ValueError(f"{name}: a run record needs 'columns' and 'dtypes' lists")
    if len(columns) != len(dtypes) or any(len(row) != len(columns) for row in rows):
        raise ValueError(
            f"{name}: {len(columns)} columns, {len(dtypes)} dtypes and rows of other lengths"
        )
    df = pd.DataFrame(rows, columns=columns)
    for col, dtype in zip(columns, dtypes, strict=True):
        values = df[col].astype(dtype)
        # A missing value of a text column is nan, as pandas.read_csv gives it.
        df[col] = values.where(values.notna(), math.nan) if dtype == "object" else values
    return record["meta"], df


def read_record(path: Path) -> tuple[dict[str, Any], pd.DataFrame]:
    """(sidecar, episodes) of the record at ``path``."""
    return decode_run(path.read_bytes(), str(path))


def read_meta(path: Path) -> dict[str, Any]:
    """The sidecar of the record at ``path`` (its episodes not parsed)."""
    meta = _record(path.read_bytes(), str(path)).get("meta")
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: a run record needs a 'meta' object")
    return meta


def read_csv_run(meta_path: Path) -> tuple[dict[str, Any], pd.DataFrame] | None:
    """(sidecar, episodes) of the run ``run`` wrote as ``meta_path`` (``seedN.json``) and
    the CSV beside it; ``None`` if it is not finished (or its sidecar is half written)."""
    try:
        meta = json.loads(meta_path.read_text())
    except ValueError:
        return None
    csv_path = meta_path.with_suffix(".csv")
    if not isinstance(meta, dict) or not meta.get("complete") or not csv_path.is_file():
        return None
    return meta, pd.read_csv(csv_path)


def archive_path(archive: Path, rel: Path) -> Path:
    """Where the run whose sidecar is ``rel`` (``.../seedN.json``, relative to its runs
    directory) is recorded in ``archive``: the same relative path, ``seedN.json.gz``."""
    return archive / rel.with_name(rel.stem + SUFFIX)


@dataclass
class AddSummary:
    """What :func:`add_runs` did."""

    added: list[Path] = field(default_factory=list)
    unchanged: list[Path] = field(default_factory=list)
    #: Recorded already with other contents: left as recorded, not overwritten.
    conflicts: list[Path] = field(default_factory=list)
    unfinished: int = 0
    invocations: int = 0

    def lines(self) -> list[str]:
        """The summary in words."""
        out = [
            f"added {len(self.added)} runs, {len(self.unchanged)} already recorded, "
            f"{self.unfinished} unfinished skipped, {self.invocations} invocation records "
            "appended"
        ]
        out += [
            f"conflict: {p} is recorded with other contents; left as it is (delete it "
            "first to replace it)"
            for p in self.conflicts
        ]
        return out


def _same(a: tuple[dict[str, Any], pd.DataFrame], b: tuple[dict[str, Any], pd.DataFrame]) -> bool:
    return a[0] == b[0] and a[1].equals(b[1])


def _write_new(path: Path, data: bytes) -> None:
    """Write ``data`` at ``path``, which must not exist (a hard link of a temporary file:
    an existing file is never replaced, and no reader sees a half-written one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    try:
        os.link(tmp, path)
    finally:
        tmp.unlink()


def add_runs(src: Path, archive: Path) -> AddSummary:
    """Record the finished runs of the ``run`` directory ``src`` in ``archive``.

    A run already recorded is left alone: counted as unchanged if its record holds the same
    sidecar and episodes, as a conflict otherwise. Lines of ``src``'s invocations log not
    yet in ``archive``'s are appended to it, in their order.
    """
    if not src.is_dir():
        raise ValueError(f"{src}: no such runs directory")
    summary = AddSummary()
    for meta_path in sorted(src.rglob("seed*.json")):
        run = read_csv_run(meta_path)
        if run is None:
            summary.unfinished += 1
            continue
        target = archive_path(archive, meta_path.relative_to(src))
        data = encode_run(*run)
        if target.exists():
            same = target.read_bytes() == data or _same(read_record(target), run)
            (summary.unchanged if same else summary.conflicts).append(target)
            continue
        _write_new(target, data)
        summary.added.append(target)
    log = src / INVOCATIONS
    if log.is_file():
        dest = archive / INVOCATIONS
        text = dest.read_text() if dest.is_file() else ""
        have = set(text.splitlines())
        new = [line for line in log.read_text().splitlines() if line and line not in have]
        if new:
            archive.mkdir(parents=True, exist_ok=True)
            # A log whose last line lacks its newline gets one first.
            sep = "\n" if text and not text.endswith("\n") else ""
            with open(dest, "a") as fh:
                fh.write(sep + "".join(line + "\n" for line in new))
        summary.invocations = len(new)
    return summary
