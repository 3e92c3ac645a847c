"""Command line: ``run`` the grid, ``report`` the results."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from tamrm_experiments.configs import ARMS, EXPERIMENTS, PROFILES, make_specs

__all__ = ["main"]

#: ``experiments/`` of the repository (defaults do not depend on the working directory).
EXPERIMENTS_DIR = Path(__file__).resolve().parents[1]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tamrm_experiments",
        description="Reproduce the TAMRM paper's experiments through the tamrm server.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run experiments x arms x seeds (resumable)")
    run.add_argument(
        "--quick", action="store_true", help="1 seed, tiny budgets: a smoke test of the pipeline"
    )
    run.add_argument("--profile", choices=sorted(PROFILES), help="budget profile (default full)")
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
        "--reverse", action="store_true", help="run the grid from its end (a second invocation)"
    )
    run.add_argument("--address", help="use a running server instead of starting one")
    run.add_argument("--no-progress", action="store_true", help="no progress bars")
    run.add_argument("--dry-run", action="store_true", help="list the runs to do and exit")

    rep = sub.add_parser("report", help="write the reproduction report from the raw runs")
    rep.add_argument("--runs", type=Path, default=EXPERIMENTS_DIR / "runs")
    rep.add_argument("--out", type=Path, default=EXPERIMENTS_DIR.parent / "docs/reproduction.md")
    rep.add_argument(
        "--plots", type=Path, help="plots directory (default: the --out path without .md)"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    args = _parser().parse_args(argv)
    if args.command == "run":
        from tamrm_experiments.run import is_complete, run_grid

        profile = args.profile or ("quick" if args.quick else "full")
        default_out = "runs-quick" if profile == "quick" else "runs"
        out = args.out or EXPERIMENTS_DIR / default_out
        specs = make_specs(profile, args.seeds, args.experiments, args.arms, args.first_seed)
        if args.reverse:
            specs.reverse()
        if args.dry_run:
            for spec in specs:
                state = "done" if is_complete(out, spec) else "todo"
                print(f"{state}  {spec.key}  {spec.budget}")
            return 0
        summary = run_grid(
            specs, out, max(1, args.jobs), address=args.address, show_progress=not args.no_progress
        )
        print(json.dumps(summary, indent=1))
        return 1 if summary["failed"] else 0
    if args.command == "report":
        from tamrm_experiments.report import write_report

        plots = args.plots or args.out.with_suffix("")
        write_report(args.runs, args.out, plots)
        print(f"wrote {args.out} and plots in {plots}/")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
