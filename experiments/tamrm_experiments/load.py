"""Runs to frames: the finished runs of a runs directory, and what its invocations asked for.

A runs directory is either what ``run`` writes (``seedN.csv`` + ``seedN.json`` sidecar) or
the committed archive (``seedN.json.gz``, :mod:`tamrm_experiments.archive`); both read the
same, and a directory may hold both as long as no run is in both.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from tamrm_experiments.archive import INVOCATIONS, SUFFIX, read_csv_run, read_record
from tamrm_experiments.args import parser
from tamrm_experiments.configs import EXPERIMENTS, make_specs, runs_variant

__all__ = [
    "Group",
    "Key",
    "Run",
    "group_runs",
    "invocations",
    "load_runs",
    "partials",
    "requested_runs",
    "wanted",
]

#: (experiment, variant, arm, seed) of a run.
Key = tuple[str, str, str, int]
#: (experiment, variant): one section of the report.
Group = tuple[str, str]


@dataclass
class Run:
    """One finished run: its sidecar and its per-episode rows."""

    experiment: str
    arm: str
    seed: int
    meta: dict[str, Any]
    df: pd.DataFrame
    variant: str = "clean"
    fidelity: str = "clean"

    @property
    def budget(self) -> dict[str, Any]:
        """The run's budget (episodes, caps)."""
        return dict(self.meta["spec"]["budget"])

    @property
    def backend(self) -> str:
        """Where its shaping was computed: ``engine`` (embedded, in process) or ``server``
        (over gRPC; every run recorded before the engine, whose sidecar has no key)."""
        return str(self.meta.get("backend", "server"))

    @property
    def key(self) -> Key:
        """(experiment, variant, arm, seed)."""
        return (self.experiment, self.variant, self.arm, self.seed)


def _run(meta: dict[str, Any], df: pd.DataFrame) -> Run:
    spec = meta["spec"]
    return Run(
        spec["experiment"],
        spec["arm"],
        spec["seed"],
        meta,
        df,
        spec.get("variant", "clean"),
        spec.get("fidelity", "clean"),
    )


def load_runs(runs_dir: Path) -> list[Run]:
    """Load every complete run under ``runs_dir`` (any depth: ``<experiment>/<variant>/
    <arm>/seedN``; runs of the first report, without a variant, count as ``clean``), in the
    order of their paths. Raises ``ValueError`` for a run recorded both as a CSV and as an
    archive record, and for a damaged record."""
    found: dict[Path, Path] = {}  # seedN.json -> the file to read
    for path in runs_dir.rglob(f"seed*{SUFFIX}"):
        found[path.with_suffix("")] = path
    for path in runs_dir.rglob("seed*.json"):
        if path in found:
            raise ValueError(
                f"{path.with_suffix('')}: recorded twice, as {path.name} (+ CSV) and as "
                f"{found[path].name}; keep one"
            )
        found[path] = path
    runs = []
    for stem in sorted(found):
        path = found[stem]
        run = read_record(path) if path.name.endswith(SUFFIX) else read_csv_run(path)
        if run is not None:
            runs.append(_run(*run))
    return runs


def invocations(runs_dir: Path) -> list[dict[str, Any]]:
    """The records of ``runs_dir``'s invocations log (unreadable lines skipped)."""
    path = runs_dir / INVOCATIONS
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def requested_runs(runs_dir: Path) -> list[Key]:
    """(experiment, variant, arm, seed) of every run that some grid invocation asked for,
    in grid order: each invocation's recorded command line parsed as the ``run`` command
    does (a command line without ``--profile`` is read with the default of its time,
    ``full``, if it has no ``--fidelity``/``--variants``: the first report's)."""
    keys: dict[Key, None] = {}
    for inv in invocations(runs_dir):
        argv = shlex.split(inv.get("command", ""))
        if "tamrm_experiments" not in argv:
            continue
        try:
            args = parser().parse_args(argv[argv.index("tamrm_experiments") + 1 :])
        except SystemExit:  # a command line this version cannot parse
            continue
        if args.command != "run":
            continue
        profile = args.profile or ("quick" if args.quick else "paper")
        for spec in make_specs(
            profile,
            args.seeds,
            args.experiments,
            args.arms,
            args.first_seed,
            args.fidelity,
            args.variants,
        ):
            keys[(spec.experiment, spec.variant, spec.arm, spec.seed)] = None
    return list(keys)


def partials(runs_dir: Path) -> dict[Key, int]:
    """Runs in progress (or interrupted): episodes written so far."""
    out = {}
    for path in runs_dir.rglob("seed*.csv.partial"):
        rel = path.relative_to(runs_dir).parts
        if len(rel) != 4:
            continue
        seed = int(rel[3].removeprefix("seed").split(".")[0])
        with open(path) as fh:
            out[(rel[0], rel[1], rel[2], seed)] = max(0, sum(1 for _ in fh) - 1)
    return out


def wanted(requested: list[Key], exp_name: str, variant: str, arm: str) -> list[int]:
    """The seeds of ``arm`` in ``variant`` that some invocation asked for: for a shared
    plain arm, those of the variant whose plain runs it uses."""
    owner = runs_variant(EXPERIMENTS[exp_name], variant, arm)
    return sorted({sd for e, v, a, sd in requested if (e, v, a) == (exp_name, owner, arm)})


def group_runs(runs: list[Run], requested: list[Key]) -> dict[Group, list[Run]]:
    """The runs of each (experiment, variant) asked for or run: its own arms, and for the
    plain arm the runs of the variant it shares plain with (``Variant.plain_from``). A
    variant's own plain runs made before it shared them are left out (see
    :func:`tamrm_experiments.grid.shared_plain`)."""
    groups: dict[Group, list[Run]] = {}
    for exp_name, exp in EXPERIMENTS.items():
        for var in exp.variants:
            rs = [
                r
                for r in runs
                if r.experiment == exp_name and r.variant == runs_variant(exp, var.name, r.arm)
            ]
            asked = any((e, v) == (exp_name, var.name) for e, v, _a, _s in requested)
            # Another variant's plain runs alone do not make a section.
            if asked or any(r.variant == var.name for r in rs):
                groups[(exp_name, var.name)] = rs
    return groups
