"""The command line's arguments: one parser, used by ``cli`` to run and by the report to
read back which runs each recorded grid invocation asked for."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from tamrm_experiments.configs import ARMS, EXPERIMENTS, FIDELITIES, PROFILES, all_variants

__all__ = ["ARCHIVE", "ARCHIVE_V1", "EXPERIMENTS_DIR", "parser"]

#: ``experiments/`` of the repository (defaults do not depend on the working directory).
EXPERIMENTS_DIR = Path(__file__).resolve().parents[1]
#: The committed runs behind ``docs/reproduction.md``, one record each (``add-runs``).
ARCHIVE = EXPERIMENTS_DIR.parent / "docs" / "reproduction" / "runs"
#: The first report's runs (shown as the ``clean-v1`` variant).
ARCHIVE_V1 = EXPERIMENTS_DIR.parent / "docs" / "reproduction" / "runs-v1"


def parser() -> argparse.ArgumentParser:
    """The ``run``, ``add-runs`` and ``report`` command line."""
    top = argparse.ArgumentParser(
        prog="python -m tamrm_experiments",
        description="Reproduce the TAMRM paper's experiments with tamrm's shaping.",
    )
    sub = top.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run experiments x arms x seeds (resumable)")
    run.add_argument(
        "--quick", action="store_true", help="1 seed, tiny budgets: a smoke test of the pipeline"
    )
    run.add_argument(
        "--profile",
        choices=sorted(PROFILES),
        help="budget profile (default paper: the paper's episode budgets)",
    )
    run.add_argument("--seeds", type=int, help="number of seeds 0..N-1 (default: the profile's)")
    run.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="skip seeds below this one (e.g. to run seed 4 in a second invocation)",
    )
    run.add_argument(
        "--jobs", type=int, default=os.cpu_count() or 1, help="parallel runs (default: all cores)"
    )
    run.add_argument(
        "--out", type=Path, help="runs directory (default experiments/runs, or runs-quick)"
    )
    run.add_argument("--experiments", nargs="+", choices=sorted(EXPERIMENTS), help="subset")
    run.add_argument("--arms", nargs="+", choices=list(ARMS), help="subset of arms")
    run.add_argument(
        "--fidelity",
        nargs="+",
        choices=list(FIDELITIES),
        help="subset: clean (SB3 learners) and/or authors (the authors' learners and settings)",
    )
    run.add_argument(
        "--variants", nargs="+", choices=all_variants(), help="subset of variants by name"
    )
    run.add_argument(
        "--reverse", action="store_true", help="run the grid from its end (a second invocation)"
    )
    run.add_argument(
        "--address",
        metavar="HOST:PORT",
        help="shape on the tamrm server at this address (default: each run on an embedded "
        "engine of its own, tamrm.Engine(), in process)",
    )
    run.add_argument(
        "--archive",
        type=Path,
        default=ARCHIVE,
        help="also skip the runs recorded with the same settings in this archive of "
        "committed runs (default docs/reproduction/runs)",
    )
    run.add_argument(
        "--no-archive", action="store_true", help="do not skip runs recorded in the archive"
    )
    run.add_argument("--no-progress", action="store_true", help="no progress bars")
    run.add_argument("--dry-run", action="store_true", help="list the runs to do and exit")

    add = sub.add_parser(
        "add-runs",
        help="record the finished runs of a runs directory in the archive of committed runs "
        "(new runs only; an existing record is never rewritten)",
    )
    add.add_argument(
        "--runs",
        type=Path,
        default=EXPERIMENTS_DIR / "runs",
        help="the runs directory `run` wrote (default experiments/runs)",
    )
    add.add_argument(
        "--to", type=Path, default=ARCHIVE, help="the archive (default docs/reproduction/runs)"
    )

    rep = sub.add_parser("report", help="write the reproduction report from the raw runs")
    rep.add_argument(
        "--runs",
        type=Path,
        help="a runs directory: the archive (seedN.json.gz) or what `run` wrote (CSV + "
        "JSON). Default: docs/reproduction/runs, with docs/reproduction/runs-v1 as "
        "--previous",
    )
    rep.add_argument("--out", type=Path, default=EXPERIMENTS_DIR.parent / "docs/reproduction.md")
    rep.add_argument(
        "--plots", type=Path, help="plots directory (default: the --out path without .md)"
    )
    rep.add_argument(
        "--previous",
        type=Path,
        help="the first report's runs directory (e.g. experiments/runs-v1): shown as clean-v1",
    )
    rep.add_argument(
        "--readme",
        type=Path,
        help="also rewrite the generated summary of the claims in this README (between its "
        "reproduction-summary markers)",
    )
    return top
