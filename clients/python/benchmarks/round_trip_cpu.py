#!/usr/bin/env python3
"""Where a remote step's time goes: the round trip after a training loop's idle gap.

A training loop calls the server once per vector step, after about a millisecond of its
own work, so every round trip meets a server (and a client runtime) that went idle. This
bench reproduces that pattern without the training: before each step the calling thread
spins for ``--gap-us`` (default 1500, an A2C CartPole vector step on the 2-core machine),
then times one round trip of an ``--envs``-env step (default 8, as the A2C benchmark).
Side by side, in rounds (the order rotating):

- ``tcp``: the ``tcp-floor`` of ``overhead.py``, a round trip of the step's size to a C
  echo on 127.0.0.1 from a Python socket (no gRPC, no HTTP/2, no shaping);
- ``engine``: the same ``Session.step`` in process (``tamrm.Engine()``): the Python
  front and the shaping, no transport;
- ``remote``: ``Session.step`` of ``tamrm.Client`` on a local in-memory server
  (``tamrm serve``, ``--server-args`` appended; e.g. ``--worker-threads 1``).

Per variant it prints the medians over rounds of: the round trip's p50 and p90, the
calling thread's CPU per step (``time.thread_time``: user and kernel, including the
loopback send's delivery to the peer, which the sender's kernel does), and for
``remote`` the server process's CPU per step (all its threads)::

    TAMRM_BIN=target/release/tamrm python clients/python/benchmarks/round_trip_cpu.py
    python clients/python/benchmarks/round_trip_cpu.py --server-args=--worker-threads=1

The results of 2026-12-04 are in docs/lab/2026-12-04-overhead.md ("Where the remote round
trip goes").
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from overhead import TcpFloor  # type: ignore[import-not-found]  # this directory

import tamrm


def spin(seconds: float) -> None:
    """Keep the CPU busy for ``seconds``, as a training step does."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def _process_cpu(pid: int) -> float:
    """CPU seconds of process ``pid`` so far: the sum over its threads of their time on a
    CPU (``/proc/PID/task/TID/schedstat``, nanoseconds; ``/proc/PID/stat`` counts in
    clock ticks, too coarse for a few thousand steps)."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        path = f"/proc/{pid}/task/{tid}/schedstat"
        with contextlib.suppress(OSError), open(path) as f:  # OSError: the thread ended
            total += int(f.read().split()[0])
    return total * 1e-9


def _timed(step: Callable[[], Any], steps: int, gap: float, warmup: int) -> dict[str, float]:
    """Round-trip percentiles (µs) and the calling thread's CPU per step (µs)."""
    for _ in range(warmup):
        step()
    lat = []
    cpu = 0.0
    for _ in range(steps):
        spin(gap)
        c0 = time.thread_time()
        t0 = time.perf_counter()
        step()
        lat.append(time.perf_counter() - t0)
        cpu += time.thread_time() - c0
    lat.sort()
    return {
        "p50_us": lat[len(lat) // 2] * 1e6,
        "p90_us": lat[int(len(lat) * 0.9)] * 1e6,
        "client_cpu_us": cpu / steps * 1e6,
    }


def _session_step(session: Any, num_envs: int) -> Callable[[], Any]:
    """One step of ``session`` (discrete actions 0, rewards 1, values 0.5)."""
    zeros = np.zeros(num_envs, dtype=np.int64)
    ones = np.ones(num_envs, dtype=np.float64)
    flags = np.zeros(num_envs, dtype=np.bool_)
    half = np.full(num_envs, 0.5, dtype=np.float64)
    return lambda: session.step(zeros, ones, flags, flags, values=half, next_values=half)


@contextlib.contextmanager
def _engine(num_envs: int) -> Iterator[Callable[[], Any]]:
    """The same step in process (``tamrm.Engine()``): no transport at all."""
    with tamrm.Engine() as engine:
        engine.create_task("bench/round_trip", num_actions=2)
        with engine.session("bench/round_trip", num_envs) as session:
            yield _session_step(session, num_envs)


@contextlib.contextmanager
def _remote(server_args: list[str], num_envs: int) -> Iterator[tuple[Callable[[], Any], int]]:
    """A local in-memory server, a task and a session; yields (step, server pid)."""
    with tamrm.local_server(in_memory=True, args=server_args) as server:
        pid = server.process.pid
        with tamrm.Client(server.address) as client:
            client.create_task("bench/round_trip", num_actions=2)
            with client.session("bench/round_trip", num_envs) as session:
                yield _session_step(session, num_envs), pid


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--gap-us", type=float, default=1500.0)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--server-args", default="", help="extra `tamrm serve` arguments")
    args = parser.parse_args()
    server_args = args.server_args.replace("=", " ").split()
    gap = args.gap_us * 1e-6
    results: dict[str, list[dict[str, float]]] = {"tcp": [], "remote": [], "engine": []}
    with tempfile.TemporaryDirectory() as tmp:
        echo = TcpFloor(tmp)
        try:
            for r in range(args.rounds):
                names = list(results)
                for name in names[r % 3 :] + names[: r % 3]:
                    if name == "engine":
                        with _engine(args.envs) as step:
                            results[name].append(_timed(step, args.steps, gap, args.warmup))
                        continue
                    if name == "tcp":
                        with echo.round_trips(args.envs) as round_trip:
                            results[name].append(_timed(round_trip, args.steps, gap, args.warmup))
                        continue
                    with _remote(server_args, args.envs) as (step, pid):
                        for _ in range(args.warmup):
                            step()
                        s0 = _process_cpu(pid)
                        row = _timed(step, args.steps, gap, 0)
                        row["server_cpu_us"] = (_process_cpu(pid) - s0) / args.steps * 1e6
                        results[name].append(row)
        finally:
            echo.close()
    print(
        f"{args.rounds} rounds of {args.steps} steps, {args.envs} envs, gap {args.gap_us:.0f} µs,"
        f" server args {server_args or 'none'}; medians over rounds"
    )
    print("| variant | RT p50 µs | RT p90 µs | client thread CPU µs/step | server CPU µs/step |")
    print("|---|---:|---:|---:|---:|")
    for name, rows in results.items():
        med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
        server = f"{med['server_cpu_us']:.1f}" if "server_cpu_us" in med else "—"
        print(
            f"| {name} | {med['p50_us']:.1f} | {med['p90_us']:.1f} |"
            f" {med['client_cpu_us']:.1f} | {server} |"
        )


if __name__ == "__main__":
    main()
