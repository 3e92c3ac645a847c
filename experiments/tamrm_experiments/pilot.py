"""Pilots of the authors' learners: does the plain learner learn within the budget?

The plain arm shapes nothing (alpha = beta = 0: the server's reward is the environment's),
so a pilot runs the authors' loop (``authors.train_authors``) with :class:`PlainSession`,
a stand-in for the server's session that returns the reward unchanged, and can try
changes to a variant's settings (``--set key=value``, JSON values) without a server::

    PYTHONPATH=experiments python -m tamrm_experiments.pilot maze authors-3 --seeds 0 1 \\
        --set obs_scale=320

It prints, per seed, the mean steps per episode over each block of ``--block`` episodes,
the first and last 20 episodes, and the total. The grid's runs go through the server;
a pilot's numbers equal the plain arm's of the same settings and seed (tested).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from tamrm_experiments.configs import EXPERIMENTS, make_specs

__all__ = ["PlainSession", "pilot"]


@dataclass
class _Result:
    rewards: list[float]
    knn_rewards: list[float]
    potentials: list[float]
    knn_active: list[bool]
    pool_version: int = 0


class PlainSession:
    """What the server's session returns to the plain arm (alpha = beta = 0): the
    environment's reward, no kNN term, no potential."""

    def step(
        self,
        actions: list[int],
        rewards: list[float],
        terminated: list[bool],
        truncated: list[bool],
        values: Any = None,
        next_values: Any = None,
        episode_scores: Any = None,
    ) -> _Result:
        n = len(actions)
        return _Result([float(r) for r in rewards], [0.0] * n, [0.0] * n, [False] * n)


def pilot(
    experiment: str,
    variant: str,
    seed: int,
    changes: dict[str, Any] | None = None,
    profile: str = "paper",
) -> list[int]:
    """Steps per episode of the plain arm of ``variant`` with ``changes`` to its settings."""
    from tamrm_experiments.authors import train_authors

    spec = make_specs(profile, seed + 1, [experiment], ["plain"], seed, variants=[variant])[0]
    if spec.fidelity != "authors":
        raise ValueError("pilots run the authors' learners (the clean ones are SB3's)")
    settings = {**EXPERIMENTS[experiment].variant(spec.variant).settings, **(changes or {})}
    steps: list[int] = []
    train_authors(spec, PlainSession(), lambda row: steps.append(row["steps"]), True, settings)
    return steps


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog="python -m tamrm_experiments.pilot")
    ap.add_argument("experiment", choices=sorted(EXPERIMENTS))
    ap.add_argument("variant")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--block", type=int, default=20, help="episodes per printed mean")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="change a setting of the variant, e.g. obs_scale=320 or "
        "learner_kwargs='{\"learn_after\": 1000}'",
    )
    args = ap.parse_args(argv)
    changes = {}
    for item in args.set:
        key, _, value = item.partition("=")
        changes[key] = json.loads(value)
    print(f"{args.experiment} {args.variant} plain, changes {json.dumps(changes)}")
    for seed in args.seeds:
        t0 = time.monotonic()
        steps = pilot(args.experiment, args.variant, seed, changes, args.profile)
        blocks = [
            round(float(np.mean(steps[i : i + args.block])))
            for i in range(0, len(steps), args.block)
        ]
        print(
            f"seed {seed}: episodes {len(steps)}, total {sum(steps):,}, first 20 "
            f"{np.mean(steps[:20]):,.1f}, last 20 {np.mean(steps[-20:]):,.1f}, "
            f"per {args.block}: {blocks} ({time.monotonic() - t0:,.0f} s)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
