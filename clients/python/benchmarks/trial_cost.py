#!/usr/bin/env python3
"""What ``tamrm-trial`` costs over training with Stable-Baselines3 directly.

Two measurements, side by side in one run:

1. **Harness overhead**: the ``plain`` arm through the trial's run function
   (``tamrm.trial.run.run_one``: env, model, episode recorder, record) against the same
   ``make_vec_env`` + model + ``learn()`` written by hand with the same seed, interleaved
   ``--repeats`` times (order alternating); the median of the per-repeat ratios. Target:
   at most 1.05.
2. **Parallel scaling**: a trial of ``2 * jobs`` plain runs with ``--jobs jobs`` worker
   processes, its wall time against the sum of the same runs' single-run times divided by
   ``jobs``. Target: at most 1.3.

::

    python clients/python/benchmarks/trial_cost.py            # CartPole A2C, 30 000 steps
    python clients/python/benchmarks/trial_cost.py --quick    # a smoke run
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


def direct(env: str, algo: str, timesteps: int, seed: int) -> float:
    """SB3 called directly: the floor."""
    import torch
    from stable_baselines3 import A2C, DQN, PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    venv = make_vec_env(env, n_envs=1, seed=seed, vec_env_cls=DummyVecEnv)
    model = {"a2c": A2C, "ppo": PPO, "dqn": DQN}[algo]("MlpPolicy", venv, seed=seed, device="cpu")
    model.learn(total_timesteps=timesteps)
    venv.close()
    return time.perf_counter() - t0


def harness(env: str, algo: str, timesteps: int, seed: int) -> float:
    """The plain arm through the trial's run function."""
    from tamrm.trial.run import run_one
    from tamrm.trial.settings import TrialSettings

    settings = TrialSettings(
        env=env, algo=algo, timesteps=timesteps, seeds=1, arms=("plain",), verdict=False
    )
    t0 = time.perf_counter()
    run_one(settings, "plain", seed)
    return time.perf_counter() - t0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env", default="CartPole-v1")
    p.add_argument("--algo", default="a2c")
    p.add_argument("--timesteps", type=int, default=30_000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)))
    p.add_argument("--quick", action="store_true", help="3 000 timesteps, 2 repeats")
    args = p.parse_args()
    if args.quick:
        args.timesteps, args.repeats = 3_000, 2
    os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "tamrm-sb3-logs"))

    ratios, d_times, h_times = [], [], []
    for rep in range(args.repeats + 1):  # the first is a warm-up
        order = [direct, harness] if rep % 2 == 0 else [harness, direct]
        times = {}
        for fn in order:
            times[fn.__name__] = fn(args.env, args.algo, args.timesteps, seed=rep)
        if rep == 0:
            continue
        d_times.append(times["direct"])
        h_times.append(times["harness"])
        ratios.append(times["harness"] / times["direct"])
        print(
            f"repeat {rep}: direct {times['direct']:.2f} s, harness {times['harness']:.2f} s",
            file=sys.stderr,
        )

    from tamrm.trial.cli import main as trial_main

    runs = 2 * args.jobs
    singles = [harness(args.env, args.algo, args.timesteps, seed) for seed in range(runs)]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        code = trial_main([
            "--env", args.env, "--algo", args.algo, "--timesteps", str(args.timesteps),
            "--seeds", str(runs), "--arms", "plain", "--no-verdict", "--jobs", str(args.jobs),
            "--no-progress", "--out", str(Path(tmp) / "t"),
        ])  # fmt: skip
        wall = time.perf_counter() - t0
    assert code == 0
    ideal = sum(singles) / args.jobs

    print(
        f"\n{args.env}, {args.algo.upper()}, {args.timesteps:,} timesteps, "
        f"{args.repeats} repeats, {os.cpu_count()} CPUs\n"
    )
    print("| measurement | floor | trial | ratio | target |")
    print("|---|---|---|---|---|")
    print(
        f"| one plain run: median wall time | SB3 directly {statistics.median(d_times):.2f} s "
        f"| {statistics.median(h_times):.2f} s | {statistics.median(ratios):.3f} | <= 1.05 |"
    )
    print(
        f"| {runs} runs on {args.jobs} jobs: wall time | sum of single runs / {args.jobs} "
        f"= {ideal:.1f} s | {wall:.1f} s (report included) | {wall / ideal:.3f} | <= 1.3 |"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
