"""Synthetic finished runs for the report's tests."""

import csv
import json
from dataclasses import replace

from tamrm_experiments.run import CSV_FIELDS, run_paths


def write_run(out, spec, steps, variant=None):
    """A finished run of ``spec`` with ``steps`` per episode (under ``variant``'s name if
    given: a run stored as an older grid stored it)."""
    if variant is not None:
        spec = replace(spec, variant=variant)
    csv_path, _, meta_path = run_paths(out, spec)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        w.writeheader()
        total = 0
        for i, n in enumerate(steps, 1):
            total += n
            w.writerow(
                {
                    "episode": i,
                    "steps": n,
                    "env_return": 1.0,
                    "shaped_return": 1.5,
                    "knn_sum": 0.1,
                    "potential_sum": 0.2,
                    "knn_active_steps": 1,
                    "terminated": 1,
                    "truncated": 0,
                    "success": 1,
                    "score": 100 / n,
                    "task_phase": 0,
                    "pool_version": i,
                    "total_steps": total,
                    "wall_time": i * 0.1,
                }
            )
    meta = {
        "spec": spec.to_dict(),
        "complete": True,
        "episodes": len(steps),
        "total_steps": sum(steps),
        "censored": False,
        "wall_time_s": 1.0,
        "steps_per_s": float(sum(steps)),
        "versions": {"cpu_count": "2"},
    }
    meta_path.write_text(json.dumps(meta))
