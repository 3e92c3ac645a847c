"""Command line: ``run`` the grid, ``add-runs`` to the committed archive, ``report``."""

from __future__ import annotations

import json
import sys

from tamrm_experiments.args import ARCHIVE, ARCHIVE_V1, EXPERIMENTS_DIR, parser
from tamrm_experiments.configs import make_specs

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    args = parser().parse_args(argv)
    if args.command == "run":
        from tamrm_experiments.run import is_complete, run_grid

        profile = args.profile or ("quick" if args.quick else "paper")
        default_out = "runs-quick" if profile == "quick" else "runs"
        out = args.out or EXPERIMENTS_DIR / default_out
        specs = make_specs(
            profile,
            args.seeds,
            args.experiments,
            args.arms,
            args.first_seed,
            getattr(args, "fidelity", None),
            getattr(args, "variants", None),
        )
        if args.reverse:
            specs.reverse()
        archive = None if args.no_archive else args.archive
        if args.dry_run:
            for spec in specs:
                state = "done" if is_complete(out, spec, archive) else "todo"
                print(f"{state}  {spec.key}  {spec.budget}")
            return 0
        summary = run_grid(
            specs,
            out,
            max(1, args.jobs),
            address=args.address,
            show_progress=not args.no_progress,
            archive=archive,
        )
        print(json.dumps(summary, indent=1))
        return 1 if summary["failed"] else 0
    if args.command == "add-runs":
        from tamrm_experiments.archive import add_runs

        added = add_runs(args.runs, args.to)
        print("\n".join(added.lines()))
        return 1 if added.conflicts else 0
    if args.command == "report":
        import os

        from tamrm_experiments.report import readme_summary, update_readme, write_report

        plots = args.plots or args.out.with_suffix("")
        runs, previous = args.runs, args.previous
        if runs is None:  # the committed runs, with the first report's
            runs = ARCHIVE
            previous = previous or ARCHIVE_V1
        analysis = write_report(runs, args.out, plots, previous)
        print(f"wrote {args.out} and plots in {plots}/")
        if args.readme:
            link = os.path.relpath(args.out, args.readme.resolve().parent)
            changed = update_readme(args.readme, readme_summary(analysis, link))
            print(f"{'updated' if changed else 'unchanged'}: the summary in {args.readme}")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
