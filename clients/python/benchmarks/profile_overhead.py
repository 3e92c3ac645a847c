#!/usr/bin/env python3
"""Where a shaped training step's time goes: perf_counter breakdowns and cProfile.

For one backend (``engine``, ``engine-dir``, ``remote``, ``remote-dir``, as in
``overhead.py``) it runs the two workloads of ``overhead.py`` once each with timers
around their parts, then once under cProfile:

- the 16-env gymnasium vector loop: ``VectorShapedReward.step`` split into the wrapped
  ``SyncVectorEnv.step``, ``Session.step`` (itself split into the native stream call and
  the Python front: checks and ``StepResult``) and the wrapper's own work;
- SB3 A2C: ``ShapedVecEnv.step_wait`` split into the wrapped ``DummyVecEnv.step_wait``,
  the bound critic (``value_fn``), ``Session.step`` and the wrapper's own work, beside
  the whole ``learn()``.

Timers are per call (``time.perf_counter_ns``), reported as totals per vector step::

    python clients/python/benchmarks/profile_overhead.py engine
    python clients/python/benchmarks/profile_overhead.py remote --no-cprofile
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import os
import pstats
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import overhead

import tamrm
import tamrm.gym


class Timers:
    def __init__(self) -> None:
        self.ns: dict[str, list[int]] = {}

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        samples = self.ns.setdefault(name, [])
        clock = time.perf_counter_ns

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                samples.append(clock() - t0)

        return timed

    def report(self, title: str, steps: int, order: list[tuple[str, str | None]]) -> None:
        print(f"\n{title}: µs per vector step ({steps} steps)")
        print("| part | total / step | median call | calls / step |\n|---|---:|---:|---:|")
        for name, minus in order:
            samples = self.ns.get(name, [])
            total = sum(samples)
            if minus:
                for m in minus.split("+"):
                    total -= sum(self.ns.get(m, []))
            med = statistics.median(samples) / 1000 if samples and not minus else float("nan")
            label = name if not minus else f"{name} minus {minus}"
            print(
                f"| {label} | {total / steps / 1000:.1f} | {med:.1f} | {len(samples) / steps:.2f} |"
            )


class TimedStream:
    """A proxy of a session's native stream that times its ``step``."""

    def __init__(self, inner: Any, timers: Timers) -> None:
        self._inner = inner
        self.step = timers.wrap("native stream step", inner.step)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def instrument_session(session: tamrm.Session, timers: Timers) -> None:
    session._native = TimedStream(session._native, timers)  # type: ignore[assignment]
    session.step = timers.wrap("Session.step", session.step)  # type: ignore[method-assign]


@contextlib.contextmanager
def backend(name: str, server: str | None) -> Iterator[Any]:
    with tempfile.TemporaryDirectory() as tmp:
        if server is not None:
            with tamrm.Client(server) as client:
                yield client
        elif name == "engine":
            with tamrm.Engine() as engine:
                yield engine
        elif name == "engine-dir":
            with tamrm.Engine(os.path.join(tmp, "engine")) as engine:
                yield engine
        elif name in ("remote", "remote-dir"):
            with (
                tamrm.local_server(in_memory=name == "remote") as local,
                tamrm.Client(local.address) as client,
            ):
                yield client
        else:
            raise SystemExit(f"unknown backend {name!r}")


def loop(be: Any, num_envs: int, steps: int, profile: bool) -> None:
    import numpy as np

    timers = Timers()
    rng = np.random.default_rng(0)
    with overhead._shaped(be, num_envs) as session:
        assert session is not None
        instrument_session(session, timers)
        inner = overhead._vector_env(num_envs)
        inner.step = timers.wrap("SyncVectorEnv.step", inner.step)  # type: ignore[method-assign]
        env = tamrm.gym.VectorShapedReward(inner, session)
        env.reset(seed=0)
        actions = rng.integers(0, 2, size=(steps, num_envs))
        outer = timers.wrap("VectorShapedReward.step", env.step)
        for t in range(steps):
            outer(actions[t])
        timers.report(
            f"{num_envs}-env loop",
            steps,
            [
                ("VectorShapedReward.step", None),
                ("SyncVectorEnv.step", None),
                ("Session.step", None),
                ("native stream step", None),
                ("Session.step", "native stream step"),
                ("VectorShapedReward.step", "SyncVectorEnv.step+Session.step"),
            ],
        )
        if profile:
            prof = cProfile.Profile()
            prof.enable()
            for t in range(steps):
                env.step(actions[t])
            prof.disable()
            print(f"\ncProfile, {num_envs}-env loop, {steps} steps (tottime, top 15):")
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)
        env.close()


def a2c(be: Any, num_envs: int, timesteps: int, profile: bool) -> None:
    import torch
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    import tamrm.sb3

    torch.set_num_threads(1)
    for run in ("timed", "cprofile") if profile else ("timed",):
        timers = Timers()
        with overhead._shaped(be, num_envs) as session:
            assert session is not None
            venv = make_vec_env("CartPole-v1", n_envs=num_envs, seed=0)
            env = tamrm.sb3.ShapedVecEnv(venv, session)
            model = A2C("MlpPolicy", env, seed=0, device="cpu")
            env.bind_model(model)
            if run == "timed":
                instrument_session(session, timers)
                venv.step_wait = timers.wrap("DummyVecEnv.step_wait", venv.step_wait)  # type: ignore[method-assign]
                critic = env.value_fn
                env.value_fn = timers.wrap("value_fn (critic)", critic)  # type: ignore[arg-type]
                env.step_wait = timers.wrap("ShapedVecEnv.step_wait", env.step_wait)  # type: ignore[method-assign]
                learn = timers.wrap("learn", model.learn)
                learn(total_timesteps=timesteps)
                steps = timesteps // num_envs
                timers.report(
                    f"SB3 A2C learn({timesteps}), {num_envs} envs",
                    steps,
                    [
                        ("learn", None),
                        ("ShapedVecEnv.step_wait", None),
                        ("DummyVecEnv.step_wait", None),
                        ("value_fn (critic)", None),
                        ("Session.step", None),
                        ("native stream step", None),
                        ("Session.step", "native stream step"),
                        (
                            "ShapedVecEnv.step_wait",
                            "DummyVecEnv.step_wait+value_fn (critic)+Session.step",
                        ),
                    ],
                )
                critic_parts(critic, env._obs)
            else:
                prof = cProfile.Profile()
                prof.enable()
                model.learn(total_timesteps=timesteps)
                prof.disable()
                print(f"\ncProfile, A2C learn({timesteps}) (cumulative, tamrm/sb3 wrapper parts):")
                stats = pstats.Stats(prof).sort_stats("cumulative")
                stats.print_stats(r"tamrm|step_wait|predict_values|forward", 15)
            env.close()


def critic_parts(critic: Any, obs: Any, calls: int = 2000) -> None:
    """Median cost of the bound critic's ``version()`` and of one evaluation (µs)."""
    clock = time.perf_counter_ns
    parts: dict[str, list[int]] = {"version()": [], "evaluation (num_envs rows)": []}
    for _ in range(calls):
        t0 = clock()
        critic.version()
        t1 = clock()
        critic(obs)
        t2 = clock()
        parts["version()"].append(t1 - t0)
        parts["evaluation (num_envs rows)"].append(t2 - t1)
    for name, samples in parts.items():
        print(f"| critic {name} | median {statistics.median(samples) / 1000:.1f} µs |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("backend", choices=("engine", "engine-dir", "remote", "remote-dir"))
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--a2c-envs", type=int, default=8)
    parser.add_argument("--a2c-timesteps", type=int, default=20000)
    parser.add_argument("--no-cprofile", action="store_true")
    parser.add_argument("--server", help="for remote/remote-dir: use this running server")
    parser.add_argument("--no-sb3", action="store_true")
    ns = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}")
    with backend(ns.backend, ns.server) as be:
        loop(be, ns.num_envs, ns.steps, not ns.no_cprofile)
        if not ns.no_sb3:
            a2c(be, ns.a2c_envs, ns.a2c_timesteps, not ns.no_cprofile)
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
