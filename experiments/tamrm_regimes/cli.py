"""The study's command line.

::

    python -m tamrm_regimes run --stage pilot          # plain PPO on every pilot variant
    python -m tamrm_regimes run --stage study          # tune, freeze, confirm, family by family
    python -m tamrm_regimes run --stage study --quick --runs /tmp/r   # the code path, tiny
    python -m tamrm_regimes report                     # docs/regimes.md from the records
    python -m tamrm_regimes rerun RECORD               # one run again: the same curve?

Every stage is resumable: a run with a record is never run again, and the settings frozen
for a family are recorded in ``frozen.json`` beside the runs the first time they are
chosen (later invocations read them back, so a confirmation never changes its settings).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from tamrm_regimes.study import (
    BUDGET,
    FULL,
    QUICK,
    Scale,
    config_id,
    confirm_keys,
    pilot_keys,
    select,
    sil_grid,
    stage_a_grid,
    stage_b_grid,
    tune_a_keys,
    tune_b_keys,
    tuned_variant,
)

REPO = Path(__file__).resolve().parents[2]
RUNS = REPO / "docs" / "regimes" / "runs"
#: Timesteps of every run in quick mode.
QUICK_TIMESTEPS = 2048


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def tuning_scores(
    runs: Path, variant: str, arm: str, seeds: tuple[int, ...]
) -> dict[str, list[float]]:
    """AUC per setting id of a tuned arm, for settings with every tuning seed recorded."""
    from tamrm.trial.analysis import run_metrics

    from tamrm_regimes.runs import read_record

    out: dict[str, list[float]] = {}
    folder = runs / "tune" / variant
    for sub in sorted(folder.glob(f"{arm}-*")):
        values = []
        for seed in seeds:
            record = read_record(sub / f"seed{seed}.json.gz")
            if record is None:
                break
            values.append(run_metrics(record, record["study"]["timesteps"], None).auc)
        else:
            out[sub.name.split("-", 1)[1]] = values
    return out


def freeze(runs: Path, family: str, scale: Scale) -> dict[str, Any]:
    """The family's frozen settings: read back if recorded, else chosen now and recorded."""
    path = runs / "frozen.json"
    frozen: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    if family in frozen:
        return dict(frozen[family])
    v = tuned_variant(family).name
    shaping_scores = tuning_scores(runs, v, "tamrm", scale.tune_seeds)
    best_a = select(shaping_scores, scale.cut(stage_a_grid()))
    grid = scale.cut(stage_a_grid()) + scale.cut(stage_b_grid(best_a))
    chosen: dict[str, Any] = {
        "shaping": select(shaping_scores, grid),
        "sil": select(tuning_scores(runs, v, "sil", scale.tune_seeds), scale.cut(sil_grid())),
    }
    chosen["shaping_id"] = config_id(chosen["shaping"])
    chosen["sil_id"] = config_id(chosen["sil"])
    frozen[family] = chosen
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(frozen, indent=1, sort_keys=True) + "\n")
    _log(f"frozen for {family}: {json.dumps(chosen, sort_keys=True)}")
    return chosen


def run_study(runs: Path, families: list[str], jobs: int, quick: bool) -> int:
    """Tune, freeze and confirm each family in turn."""
    from tamrm_regimes.runs import run_keys

    scale = QUICK if quick else FULL
    timesteps = QUICK_TIMESTEPS if quick else None
    failed = 0
    for family in families:
        v = tuned_variant(family).name
        _log(f"== {family}: stage A of the shaping grid, SIL's grid and plain on {v}")
        failed += run_keys(tune_a_keys(family, scale), runs, jobs, timesteps)["failed"]
        best_a = select(
            tuning_scores(runs, v, "tamrm", scale.tune_seeds), scale.cut(stage_a_grid())
        )
        _log(f"== {family}: stage B around {json.dumps(best_a, sort_keys=True)}")
        failed += run_keys(tune_b_keys(family, best_a, scale), runs, jobs, timesteps)["failed"]
        frozen = freeze(runs, family, scale)
        _log(f"== {family}: confirmation")
        keys = confirm_keys(family, frozen["shaping"], frozen["sil"], scale)
        failed += run_keys(keys, runs, jobs, timesteps)["failed"]
    return 1 if failed else 0


def rerun_record(path: Path) -> int:
    """Run the run of a record again from its settings; 0 when the episodes are the same."""
    from tamrm_regimes.runs import read_record, rerun

    record = read_record(path)
    if record is None:
        _log(f"{path}: not a run record")
        return 2
    again = rerun(record)
    same = (
        again["episodes"] == record["episodes"]
        and again["policy_sha256"] == record["policy_sha256"]
    )
    n = len(record["episodes"]["return"])
    _log(f"{path}: {'the same curve' if same else 'A DIFFERENT CURVE'} ({n} episodes)")
    return 0 if same else 1


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    p = argparse.ArgumentParser(
        prog="python -m tamrm_regimes",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a stage's missing runs (resumable)")
    run.add_argument("--stage", required=True, choices=("pilot", "study"))
    run.add_argument("--families", default="E1,E3,E2", help="in this order [E1,E3,E2]")
    run.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)))
    run.add_argument("--runs", type=Path, default=RUNS)
    run.add_argument("--quick", action="store_true", help="the code path with tiny runs")
    run.add_argument("--dry-run", action="store_true", help="list the pilot's runs")
    report = sub.add_parser("report", help="write the results page from the records")
    report.add_argument("--runs", type=Path, default=RUNS)
    report.add_argument("--out", type=Path, default=REPO / "docs" / "regimes.md")
    report.add_argument("--quick", action="store_true", help="records of a --quick run")
    rerun = sub.add_parser("rerun", help="run one recorded run again and compare its episodes")
    rerun.add_argument("record", type=Path)
    args = p.parse_args(argv)
    if args.command == "rerun":
        return rerun_record(args.record)
    if args.command == "report":
        from tamrm_regimes.report import write_report

        write_report(args.runs, args.out, QUICK if args.quick else FULL)
        return 0
    if args.stage == "pilot":
        from tamrm_regimes.runs import run_keys

        keys = pilot_keys()
        if args.dry_run:
            for key in keys:
                print(("done " if (args.runs / key.path).is_file() else "todo ") + key.path)
            return 0
        return 1 if run_keys(keys, args.runs, args.jobs)["failed"] else 0
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = [f for f in families if f not in BUDGET]
    if unknown:
        p.error(f"--families: unknown {', '.join(unknown)} (of {', '.join(BUDGET)})")
    return run_study(args.runs, families, args.jobs, args.quick)
