#!/usr/bin/env python3
"""Measure what shaping through tamrm costs a training loop.

1. A 16-env CartPole-v1 gymnasium vector loop (random actions): plain, shaped with
   ``VectorShapedReward`` (no values), and shaped with a value function (a small numpy
   linear critic, so that the cost measured is the client's and the server's).
2. A Stable-Baselines3 A2C training run on CartPole-v1, plain and through
   ``ShapedVecEnv`` with the model's own values bound.

Each configuration is run ``--repeats`` times; the medians are reported as a markdown
table (paste it into docs/python.md). Run on an otherwise idle machine::

    python clients/python/benchmarks/overhead.py            # full
    python clients/python/benchmarks/overhead.py --quick    # a fast smoke run
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import time
import uuid
from collections.abc import Callable, Iterator

import gymnasium as gym
import numpy as np

import tamrm
import tamrm.gym


def _vector_env(num_envs: int) -> gym.vector.SyncVectorEnv:
    return gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1") for _ in range(num_envs)])


def _linear_value(obs: np.ndarray) -> np.ndarray:
    return np.asarray(obs, dtype=np.float64) @ np.array([0.1, -0.2, 0.3, 0.05])


@contextlib.contextmanager
def _shaped(client: tamrm.Client | None, num_envs: int) -> Iterator[tamrm.Session | None]:
    if client is None:
        yield None
        return
    task_id = f"bench/{uuid.uuid4().hex[:12]}"
    client.create_task(task_id, num_actions=2)
    try:
        with client.session(task_id, num_envs) as session:
            yield session
    finally:
        client.delete_task(task_id)


def vector_loop(client: tamrm.Client | None, num_envs: int, steps: int, with_values: bool) -> float:
    """Seconds for ``steps`` vector steps of ``num_envs`` CartPoles."""
    rng = np.random.default_rng(0)
    with _shaped(client, num_envs) as session:
        env: gym.vector.VectorEnv = _vector_env(num_envs)
        if session is not None:
            env = tamrm.gym.VectorShapedReward(
                env, session, value_fn=_linear_value if with_values else None
            )
        env.reset(seed=0)
        actions = rng.integers(0, 2, size=(steps, num_envs))
        start = time.perf_counter()
        for t in range(steps):
            env.step(actions[t])
        elapsed = time.perf_counter() - start
        env.close()
    return elapsed


def a2c_run(client: tamrm.Client | None, num_envs: int, timesteps: int) -> float:
    """Seconds for an A2C ``learn(timesteps)`` on CartPole-v1."""
    import torch
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    import tamrm.sb3

    torch.set_num_threads(1)
    with _shaped(client, num_envs) as session:
        venv = make_vec_env("CartPole-v1", n_envs=num_envs, seed=0)
        env = venv if session is None else tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env, seed=0, device="cpu")
        if isinstance(env, tamrm.sb3.ShapedVecEnv):
            env.bind_model(model)
        start = time.perf_counter()
        model.learn(total_timesteps=timesteps)
        elapsed = time.perf_counter() - start
        env.close()
    return elapsed


def median_of(repeats: int, run: Callable[[], float]) -> tuple[float, list[float]]:
    """Median (and all samples) of ``repeats`` runs, after one warm-up run."""
    run()
    samples = [run() for _ in range(repeats)]
    return statistics.median(samples), samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1000, help="vector steps per loop run")
    parser.add_argument("--a2c-envs", type=int, default=8)
    parser.add_argument("--a2c-timesteps", type=int, default=20000)
    parser.add_argument("--no-sb3", action="store_true", help="skip the A2C runs")
    parser.add_argument("--quick", action="store_true", help="small sizes, 2 repeats")
    ns = parser.parse_args()
    if ns.quick:
        ns.repeats, ns.steps, ns.a2c_timesteps = 2, 300, 4000

    with contextlib.ExitStack() as stack:
        servers: dict[str, tamrm.Client] = {}
        if ns.server:
            servers["server"] = stack.enter_context(tamrm.Client(ns.server))
        else:
            durable = stack.enter_context(tamrm.local_server())
            memory = stack.enter_context(tamrm.local_server(in_memory=True))
            servers["--data-dir"] = stack.enter_context(tamrm.Client(durable.address))
            servers["in-memory"] = stack.enter_context(tamrm.Client(memory.address))

        rows: list[tuple[str, str, float, float]] = []
        n, steps = ns.num_envs, ns.steps
        loop = f"{n}-env CartPole-v1 loop, {steps} vector steps"
        base, _ = median_of(ns.repeats, lambda: vector_loop(None, n, steps, False))
        rows.append((loop, "plain", base, n * steps / base))
        for label, client in servers.items():
            for with_values in (False, True):
                secs, _ = median_of(
                    ns.repeats,
                    lambda c=client, v=with_values: vector_loop(c, n, steps, v),  # type: ignore[misc]
                )
                name = f"shaped{' + value_fn' if with_values else ''} ({label})"
                rows.append((loop, name, secs, n * steps / secs))

        if not ns.no_sb3:
            k, ts = ns.a2c_envs, ns.a2c_timesteps
            a2c = f"SB3 A2C learn({ts}), {k} envs"
            a2c_base, _ = median_of(ns.repeats, lambda: a2c_run(None, k, ts))
            rows.append((a2c, "plain", a2c_base, ts / a2c_base))
            for label, client in servers.items():
                secs, _ = median_of(ns.repeats, lambda c=client: a2c_run(c, k, ts))  # type: ignore[misc]
                rows.append((a2c, f"ShapedVecEnv + bind_model ({label})", secs, ts / secs))

    print(
        f"\nmachine: {platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; median of {ns.repeats} runs (after 1 warm-up)\n"
    )
    print("| workload | variant | median time (s) | env steps/s | overhead per vector step |")
    print("|---|---|---:|---:|---:|")
    baselines: dict[str, tuple[float, int]] = {}
    for workload, name, secs, rate in rows:
        vector_steps = steps if "loop" in workload else ns.a2c_timesteps // ns.a2c_envs
        if name == "plain":
            baselines[workload] = (secs, vector_steps)
            extra = "—"
        else:
            base_secs, vsteps = baselines[workload]
            per_step_us = (secs - base_secs) / vsteps * 1e6
            extra = f"{per_step_us:+.0f} µs ({(secs / base_secs - 1) * 100:+.0f}%)"
        print(f"| {workload} | {name} | {secs:.3f} | {rate:,.0f} | {extra} |")


if __name__ == "__main__":
    main()
