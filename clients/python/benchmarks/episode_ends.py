#!/usr/bin/env python3
"""What episode ends cost a local session: ``Session.step`` on a trace full of them.

A local session (SPEC §13) shapes in-process, so a step that ends no episode costs what
the Engine's does; a step that ends one plans the pool change and sends it, and waits
for the server only when a change meets another unanswered one. This bench replays one
fixed trace (``--envs`` discrete CartPole-like environments, values given, episodes of
10 to 200 steps growing over the run, as a learner's do) on each variant, in rounds (the
order fixed, every variant once per round, after a warm-up round), with ``--gap-us`` of
spinning before each step (a training loop's own work; 0: back to back):

- ``engine``: ``tamrm.Engine()``, in memory (no server);
- ``local``: ``Client.session(..., local=True)`` on a local server in memory;
- ``local-dir``: the same on a server with a data directory (every ack after an fsync);
- ``local-shm``: the same with the data directory on ``/dev/shm`` (an fsync costs
  nothing: what is left is the durable commit's own work).

Per variant it prints the medians over rounds of: the mean step time, the p50 of the
steps that end no episode and of those that end one, the mean and p99 of the latter,
and the mean step time's difference from the Engine's in the same round::

    TAMRM_BIN=target/release/tamrm python clients/python/benchmarks/episode_ends.py
    python clients/python/benchmarks/episode_ends.py --gap-us 0 --rounds 5
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable
from typing import Any

import numpy as np
from round_trip_cpu import spin  # type: ignore[import-not-found]  # this directory

import tamrm

VARIANTS = ("engine", "local", "local-dir", "local-shm")

Trace = list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def make_trace(num_envs: int, steps: int, seed: int = 0) -> Trace:
    """Per vector step: actions, rewards, terminated, values, next values."""
    rng = np.random.default_rng(seed)
    left = rng.integers(10, 30, num_envs)
    trace: Trace = []
    for t in range(steps):
        left -= 1
        ended = left == 0
        longest = 20 + 180 * t // steps
        left[ended] = rng.integers(10, longest, int(ended.sum()))
        trace.append(
            (
                rng.integers(0, 2, num_envs).astype(np.int64),
                np.ones(num_envs),
                ended,
                rng.normal(size=num_envs),
                rng.normal(size=num_envs),
            )
        )
    return trace


def replay(session: tamrm.Session, trace: Trace, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Step times (ns) and whether each step ended an episode."""
    times = np.empty(len(trace), dtype=np.int64)
    ends = np.empty(len(trace), dtype=bool)
    for i, (actions, rewards, ended, values, next_values) in enumerate(trace):
        spin(gap)
        any_end = bool(ended.any())
        t0 = time.perf_counter_ns()
        session.step(
            actions,
            rewards,
            terminated=ended if any_end else None,
            values=values,
            next_values=next_values,
        )
        times[i] = time.perf_counter_ns() - t0
        ends[i] = any_end
    return times, ends


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=2500, help="vector steps per replay")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--gap-us", type=float, default=1000.0)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    ns = parser.parse_args()
    names = [v for v in ns.variants.split(",") if v]
    unknown = set(names) - set(VARIANTS)
    if unknown:
        parser.error(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
    trace = make_trace(ns.envs, ns.steps)
    n = ns.envs
    with contextlib.ExitStack() as stack:
        backends: dict[str, tuple[Any, Callable[[str], tamrm.Session]]] = {}
        for name in names:
            if name == "engine":
                engine = stack.enter_context(tamrm.Engine())
                backends[name] = (engine, functools.partial(engine.session, num_envs=n))
                continue
            if name == "local":
                server = stack.enter_context(tamrm.local_server(in_memory=True))
            elif name == "local-dir":
                server = stack.enter_context(tamrm.local_server())
            else:
                shm = stack.enter_context(tempfile.TemporaryDirectory(dir="/dev/shm"))
                server = stack.enter_context(tamrm.local_server(data_dir=shm))
            client = stack.enter_context(tamrm.Client(server.address))
            backends[name] = (client, functools.partial(client.session, num_envs=n, local=True))
        rows: dict[str, list[dict[str, float]]] = {name: [] for name in names}
        for r in range(ns.rounds + 1):
            means: dict[str, float] = {}
            for name, (backend, open_session) in backends.items():
                task = f"bench/{uuid.uuid4().hex[:12]}"
                backend.create_task(task, num_actions=2)
                with open_session(task) as session:
                    times, ends = replay(session, trace, ns.gap_us / 1e6)
                backend.delete_task(task)
                us = times / 1e3
                means[name] = float(us.mean())
                if r:  # round 0 warms up
                    rows[name].append(
                        {
                            "mean": means[name],
                            "no_end_p50": float(np.median(us[~ends])),
                            "end_p50": float(np.median(us[ends])),
                            "end_mean": float(us[ends].mean()),
                            "end_p99": float(np.percentile(us[ends], 99)),
                            "vs_engine": means[name] - means.get("engine", np.nan),
                        }
                    )
    ended = sum(bool(e.any()) for _, _, e, _, _ in trace)
    print(
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {os.cpu_count()} CPUs; "
        f"{n} envs, {ns.steps} vector steps ({ended} end an episode), gap {ns.gap_us:g} µs, "
        f"{ns.rounds} rounds; medians over rounds, µs"
    )
    print("| variant | mean step | no end p50 | end p50 | end mean | end p99 | mean - Engine |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, samples in rows.items():
        m = {k: statistics.median(s[k] for s in samples) for k in samples[0]}
        print(
            f"| {name} | {m['mean']:.1f} | {m['no_end_p50']:.1f} | {m['end_p50']:.1f} | "
            f"{m['end_mean']:.1f} | {m['end_p99']:.1f} | {m['vs_engine']:+.1f} |"
        )


if __name__ == "__main__":
    main()
