#!/usr/bin/env python3
"""Where ShapedVecEnv's time goes inside a real SB3 training loop, fast path included.

``profile_overhead.py`` wraps the bound critic to time it, which turns the one-call fast
path off; this script leaves the wrapper as it is and times, at the instance level,
the wrapped ``DummyVecEnv.step_wait``, ``ShapedVecEnv.step_wait`` and its native call
during an A2C ``learn(20000)`` on 8 CartPole-v1 envs shaped by each of ``--variants``
(alpha = beta = 0, so the shaped runs learn exactly what the plain run learns), beside a
plain run: ``engine`` (an embedded engine), ``local`` and ``local-dir`` (a
``Client.session(..., local=True)`` on a local server in memory, or with a data
directory). It also times the policy's forward pass and ``A2C.train`` in every run: what
they gain in a shaped run is cost the wrapper causes outside its own code (the same
torch work, run after the wrapper's). Each round runs plain, then every variant::

    python clients/python/benchmarks/fast_path_timers.py --rounds 3
    python clients/python/benchmarks/fast_path_timers.py --variants engine,local,local-dir
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from stable_baselines3 import A2C
from stable_baselines3.common.env_util import make_vec_env

import tamrm
import tamrm.sb3

sys.path.insert(0, str(Path(__file__).resolve().parent))

from profile_overhead import Timers


def run(backend: tamrm.Engine | tamrm.Client | None, timesteps: int) -> dict[str, Any]:
    torch.set_num_threads(1)
    venv = make_vec_env("CartPole-v1", n_envs=8, seed=0)
    env: Any = venv
    session = None
    if backend is not None:
        backend.create_task("timers", num_actions=2, alpha=0.0, beta=0.0)
        if isinstance(backend, tamrm.Client):
            session = backend.session("timers", 8, local=True)
        else:
            session = backend.session("timers", 8)
        env = tamrm.sb3.ShapedVecEnv(venv, session)
    model = A2C("MlpPolicy", env, seed=0, device="cpu")
    timers = Timers()
    venv.step_wait = timers.wrap("inner", venv.step_wait)  # type: ignore[method-assign]
    model.policy.forward = timers.wrap("forward", model.policy.forward)
    model.train = timers.wrap("train", model.train)  # type: ignore[method-assign]
    if session is not None:
        env.bind_model(model)
        # The native fast path's one call (a stand-in object, so it can be wrapped).
        env._vec_step = SimpleNamespace(step=timers.wrap("fast", env._vec_step.step))
        env.step_wait = timers.wrap("outer", env.step_wait)
    start = time.perf_counter()
    model.learn(total_timesteps=timesteps)
    elapsed = time.perf_counter() - start
    if session is not None and backend is not None:
        session.close()
        backend.delete_task("timers")
    ns = timers.ns
    return {
        "s": elapsed,
        **{k: ns.get(k, []) for k in ("inner", "outer", "fast", "forward", "train")},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--timesteps", type=int, default=20000)
    parser.add_argument("--variants", default="engine", help="engine, local, local-dir")
    ns = parser.parse_args()
    steps = ns.timesteps // 8
    us = 1e-3
    with contextlib.ExitStack() as stack:
        backends: dict[str, tamrm.Engine | tamrm.Client] = {}
        for name in ns.variants.split(","):
            if name == "engine":
                backends[name] = stack.enter_context(tamrm.Engine())
            elif name in ("local", "local-dir"):
                server = stack.enter_context(tamrm.local_server(in_memory=name == "local"))
                backends[name] = stack.enter_context(tamrm.Client(server.address))
            else:
                parser.error(f"unknown variant {name!r}")
        for r in range(ns.rounds):
            plain = run(None, ns.timesteps)
            for name, backend in backends.items():
                shaped = run(backend, ns.timesteps)
                wrapper = (sum(shaped["outer"]) - sum(shaped["inner"])) / steps * us
                fast = shaped["fast"]
                # Per vector step, shaped minus plain: the same torch work, slower or not.
                torch_extra = {
                    k: (sum(shaped[k]) - sum(plain[k])) / steps * us for k in ("forward", "train")
                }
                print(
                    f"round {r + 1}, {name}: learn plain {plain['s']:.3f} s, shaped "
                    f"{shaped['s']:.3f} s (+{(shaped['s'] - plain['s']) / steps * 1e6:.0f} µs "
                    f"per vector step); DummyVecEnv.step_wait "
                    f"{sum(plain['inner']) / steps * us:.1f} / "
                    f"{sum(shaped['inner']) / steps * us:.1f} µs per step (plain / shaped); "
                    f"ShapedVecEnv's own work {wrapper:.1f} µs per step; fast path "
                    f"{len(fast)} of {steps} steps, p50 {statistics.median(fast) * us:.1f} µs, "
                    f"mean {statistics.fmean(fast) * us:.1f} µs; the same torch work per "
                    f"vector step, shaped minus plain: forward {torch_extra['forward']:+.1f} µs, "
                    f"train {torch_extra['train']:+.1f} µs"
                )


if __name__ == "__main__":
    main()
