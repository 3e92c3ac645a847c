#!/usr/bin/env python3
"""``Session.step`` latency of every tamrm client, side by side, against one server.

One in-memory server (``tamrm.local_server(in_memory=True)``) and one task (discrete
n = 2, |D| = 30, k = 20, kNN active from step 0: the pool is seeded with 30 random
trajectories of 10 000-12 000 actions, as in ``benches/loadgen.rs`` but longer). Each
client runs in its own process, in turn, ``--rounds`` times (the order rotating each
round): it opens a session of ``N`` envs, sends ``--warmup`` untimed steps, then
``--steps`` timed ones, and reports p50/p90/p99 of the round trip of one ``step`` (arrays
already in the canonical dtypes: int64 actions, float64 rewards and values, bool flags;
no episode ends, so the pool does not change during the run). Clients:

- ``engine``: ``tamrm.Engine()`` (in-process, its own task seeded the same way; no server);
- ``local``: ``tamrm.Client.session(..., local=True)`` (SPEC §13: shaped in-process
  against a followed copy of the server's pool; no round trip while no episode ends);
- ``native``: ``tamrm.Client`` (the native extension: tonic, GIL released);
- ``native-poll``: the same with ``busy_poll_us=200`` (polls for the answer, no sleep);
- ``aio``: ``tamrm.aio.Client`` of this checkout, under asyncio;
- ``grpcio-sync`` / ``grpcio-aio``: the pure-grpcio ``tamrm.Client`` / ``tamrm.aio.Client``
  as they were before the native extension (commit ``32108c1``, extracted with
  ``git archive`` into a temporary directory and imported from there; skipped without git);
- ``rust``: ``benches/step_latency.rs``, the generated tonic client, on the same server.

Prints a markdown table: per client and N, the median over rounds of p50 and p99, the
range of p50 over rounds, and the ratio of p50 and p99 to the Rust client's (median
over rounds of the per-round ratio)::

    python clients/python/benchmarks/step_latency.py                 # 1 and 16 envs, 3 rounds
    python clients/python/benchmarks/step_latency.py --envs 16 --rounds 1 --steps 2000
    python clients/python/benchmarks/step_latency.py --profile native --envs 16

``--profile CLIENT`` runs one client once under cProfile and prints a perf_counter
breakdown of ``Session.step`` (the Python front vs the native call) and the top functions.
The Rust bench is built with ``cargo bench --bench step_latency --no-run`` (honouring
``CARGO_TARGET_DIR``) unless ``--rust-bench PATH`` names the executable.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve()
REPO = HERE.parents[3]
OLD_COMMIT = "32108c1"  # the last commit whose Python client was pure grpcio
TASK = "bench/step_latency"
CLIENTS = (
    "engine",
    "local",
    "native",
    "native-poll",
    "aio",
    "grpcio-sync",
    "grpcio-aio",
    "rust",
)
#: ``busy_poll_us`` of the ``native-poll`` client.
BUSY_POLL_US = 200


# -- the workload (identical in every client) -------------------------------------------


def task_config() -> dict[str, Any]:
    return {"num_actions": 2, "pool_capacity": 30, "k": 20, "start_step": 0}


def seed_pool(client: Any, task_id: str) -> None:
    """30 random trajectories of 10 000-12 000 actions, scores 200-500 (seeded).

    Longer than any timed episode (warm-up + steps <= 10 000), so kNN is active at every
    timed step (it stops at the shortest stored trajectory's length, SPEC §2).
    """
    rng = np.random.default_rng(7)
    for _ in range(30):
        length = int(rng.integers(10_000, 12_001))
        client.add_trajectory(
            task_id, rng.integers(0, 2, size=length), float(rng.uniform(200, 500))
        )


def inputs(num_envs: int, steps: int) -> dict[str, Any]:
    rng = np.random.default_rng(11)
    return {
        "actions": rng.integers(0, 2, size=(steps, num_envs)).astype(np.int64),
        "rewards": np.ones(num_envs, dtype=np.float64),
        "terminated": np.zeros(num_envs, dtype=np.bool_),
        "truncated": np.zeros(num_envs, dtype=np.bool_),
        "values": np.full(num_envs, 0.5, dtype=np.float64),
        "next_values": np.full(num_envs, 0.6, dtype=np.float64),
    }


def percentile(sorted_us: list[float], q: float) -> float:
    """Nearest rank (numpy's "inverted_cdf"), as benches/step_latency.rs computes it."""
    rank = min(max(math.ceil(q * len(sorted_us)), 1), len(sorted_us))
    return sorted_us[rank - 1]


def summary(name: str, num_envs: int, lat_ns: list[int], knn: float) -> dict[str, Any]:
    us = sorted(x / 1000 for x in lat_ns)
    return {
        "client": name,
        "envs": num_envs,
        "steps": len(us),
        "p50_us": percentile(us, 0.5),
        "p90_us": percentile(us, 0.9),
        "p99_us": percentile(us, 0.99),
        "mean_us": statistics.fmean(us),
        "knn_active": knn,
    }


# -- workers (one process per client and run) --------------------------------------------


class Recorder:
    """The timed steps' latencies (ns) and how many of their entries had kNN active."""

    def __init__(self, warmup: int) -> None:
        self.warmup = warmup
        self.lat: list[int] = []
        self.active = 0
        self.entries = 0

    def add(self, i: int, dt: int, result: Any) -> None:
        if i >= self.warmup:
            self.lat.append(dt)
            self.active += int(np.count_nonzero(result.knn_active))
            self.entries += len(result.knn_active)

    def done(self) -> tuple[list[int], float]:
        return self.lat, self.active / max(self.entries, 1)


def step_args(data: dict[str, Any]) -> tuple[Any, tuple[Any, ...], dict[str, Any]]:
    """Per-step actions, then the positional and keyword arguments every step shares."""
    flags = (data["rewards"], data["terminated"], data["truncated"])
    return data["actions"], flags, {"values": data["values"], "next_values": data["next_values"]}


def sync_loop(
    session: Any, data: dict[str, Any], warmup: int, steps: int
) -> tuple[list[int], float]:
    acts, flags, values = step_args(data)
    rec, clock = Recorder(warmup), time.perf_counter_ns
    for i in range(warmup + steps):
        a = acts[i]
        t0 = clock()
        result = session.step(a, *flags, **values)
        rec.add(i, clock() - t0, result)
    return rec.done()


async def async_loop(
    session: Any, data: dict[str, Any], warmup: int, steps: int
) -> tuple[list[int], float]:
    acts, flags, values = step_args(data)
    rec, clock = Recorder(warmup), time.perf_counter_ns
    for i in range(warmup + steps):
        a = acts[i]
        t0 = clock()
        result = await session.step(a, *flags, **values)
        rec.add(i, clock() - t0, result)
    return rec.done()


def worker(ns: argparse.Namespace) -> dict[str, Any]:
    import tamrm

    data = inputs(ns.envs, ns.warmup + ns.steps)
    name = ns.worker
    if name == "engine":
        with tamrm.Engine() as engine:
            engine.create_task(TASK, **task_config())
            seed_pool(engine, TASK)
            with engine.session(TASK, ns.envs) as session:
                lat, knn = sync_loop(session, data, ns.warmup, ns.steps)
    elif name == "local":
        with (
            tamrm.Client(ns.addr) as client,
            client.session(ns.task, ns.envs, local=True) as session,
        ):
            lat, knn = sync_loop(session, data, ns.warmup, ns.steps)
    elif name in ("native", "native-poll", "grpcio-sync"):
        poll = {"busy_poll_us": BUSY_POLL_US} if name == "native-poll" else {}
        with (
            tamrm.Client(ns.addr, **poll) as client,  # type: ignore[arg-type]
            client.session(ns.task, ns.envs) as session,
        ):
            lat, knn = sync_loop(session, data, ns.warmup, ns.steps)
    elif name in ("aio", "grpcio-aio"):
        import tamrm.aio

        async def run() -> tuple[list[int], float]:
            async with (
                tamrm.aio.Client(ns.addr) as client,
                client.session(ns.task, ns.envs) as session,
            ):
                return await async_loop(session, data, ns.warmup, ns.steps)

        lat, knn = asyncio.run(run())
    else:
        raise SystemExit(f"unknown worker {name!r}")
    out = summary(name, ns.envs, lat, knn)
    out["module"] = tamrm.__file__
    if name == "aio":
        import inspect

        import tamrm.aio

        out["aio_transport"] = "grpcio" if "grpc.aio" in inspect.getsource(tamrm.aio) else "native"
    return out


# -- profiling a client ------------------------------------------------------------------


def profile(ns: argparse.Namespace, addr: str) -> None:
    """perf_counter breakdown and cProfile of ``Session.step`` for one sync client."""
    import cProfile
    import pstats

    import tamrm

    data = inputs(ns.envs, ns.warmup + ns.steps)
    if ns.profile == "engine":
        owner: Any = tamrm.Engine()
        owner.create_task(TASK, **task_config())
        seed_pool(owner, TASK)
        task = TASK
    elif ns.profile == "native":
        owner = tamrm.Client(addr)
        task = ns.task
    else:
        raise SystemExit("--profile takes engine or native")
    acts = data["actions"]
    rew, term, trunc = data["rewards"], data["terminated"], data["truncated"]
    v, nv = data["values"], data["next_values"]
    clock = time.perf_counter_ns
    with owner, owner.session(task, ns.envs) as session:
        sync_loop(session, data, ns.warmup, ns.steps)  # warm
        raw = session._native  # the native stream under the Python front
        parts: dict[str, list[int]] = {"Session.step": [], "native step call": [], "StepResult": []}
        rows = session._all_rows
        for i in range(ns.steps):
            a = acts[i]
            t0 = clock()
            session.step(a, rew, term, trunc, values=v, next_values=nv)
            t1 = clock()
            ans = raw.step(None, a, rew, term, trunc, v, nv, None, None, None, None)
            t2 = clock()
            tamrm.StepResult(ans[0], ans[1], ans[2], ans[3], ans[4], ans[5], rows)
            t3 = clock()
            parts["Session.step"].append(t1 - t0)
            parts["native step call"].append(t2 - t1)
            parts["StepResult"].append(t3 - t2)
        print(f"\nperf_counter breakdown, {ns.profile}, {ns.envs} envs, {ns.steps} steps (µs):")
        print("| part | p50 | p99 | mean |\n|---|---:|---:|---:|")
        for part, lat in parts.items():
            us = sorted(x / 1000 for x in lat)
            print(
                f"| {part} | {percentile(us, 0.5):.1f} | {percentile(us, 0.99):.1f} "
                f"| {statistics.fmean(us):.1f} |"
            )
        front = statistics.median(parts["Session.step"]) - statistics.median(
            parts["native step call"]
        )
        print(f"Python front (Session.step p50 - native call p50): {front / 1000:.1f} µs")
        prof = cProfile.Profile()
        prof.enable()
        sync_loop(session, data, 0, ns.steps)
        prof.disable()
    print(f"\ncProfile of {ns.steps} steps (tottime):")
    pstats.Stats(prof).sort_stats("tottime").print_stats(12)


# -- the orchestrator --------------------------------------------------------------------


def old_client_dir(tmp: Path) -> Path | None:
    """The pure-grpcio client of ``OLD_COMMIT``, extracted; ``None`` if git cannot."""
    target = tmp / "old"
    target.mkdir()
    try:
        archive = subprocess.run(
            ["git", "-C", str(REPO), "archive", OLD_COMMIT, "clients/python/src"],
            check=True,
            capture_output=True,
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"grpcio clients skipped: {exc}", file=sys.stderr)
        return None
    return target / "clients" / "python" / "src"


def rust_bench_path(explicit: str | None) -> str | None:
    if explicit:
        return explicit
    try:
        out = subprocess.run(
            ["cargo", "bench", "--bench", "step_latency", "--no-run", "--message-format=json"],
            cwd=REPO,
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"rust client skipped: {exc}", file=sys.stderr)
        return None
    for line in out.splitlines():
        msg = json.loads(line)
        artifact = msg.get("reason") == "compiler-artifact" and msg.get("executable")
        if artifact and msg["target"]["name"] == "step_latency":
            return str(msg["executable"])
    return None


def run_client(
    name: str, num_envs: int, ns: argparse.Namespace, addr: str, old: Path | None, rust: str | None
) -> dict[str, Any] | None:
    common = ["--envs", str(num_envs), "--steps", str(ns.steps), "--warmup", str(ns.warmup)]
    env = dict(os.environ)
    if name == "rust":
        if rust is None:
            return None
        cmd = [rust, "--addr", addr, "--task", ns.task, *common]
    else:
        cmd = [sys.executable, str(HERE), "--worker", name, "--addr", addr, "--task", ns.task]
        cmd += common
        if name.startswith("grpcio"):
            if old is None:
                return None
            env["PYTHONPATH"] = os.pathsep.join([str(old), env.get("PYTHONPATH", "")])
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        print(f"{name} ({num_envs} envs) failed:\n{proc.stderr[-2000:]}", file=sys.stderr)
        return None
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    result["client"] = name
    return result


LABELS = {
    "engine": "`tamrm.Engine()` (in-process)",
    "local": "`tamrm.Client` session(local=True)",
    "native": "`tamrm.Client` (native, tonic)",
    "native-poll": f"`tamrm.Client(busy_poll_us={BUSY_POLL_US})`",
    "aio": "`tamrm.aio.Client` (asyncio)",
    "grpcio-sync": f"pure-grpcio `tamrm.Client` (`{OLD_COMMIT}`)",
    "grpcio-aio": f"pure-grpcio `tamrm.aio.Client` (`{OLD_COMMIT}`)",
    "rust": "Rust tonic client (`benches/step_latency.rs`)",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", default="1,16", help="comma-separated env counts")
    parser.add_argument("--steps", type=int, default=5000, help="timed steps per run")
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--clients", default=",".join(CLIENTS))
    parser.add_argument("--server", help="use this server (host:port) instead of a local one")
    parser.add_argument("--rust-bench", help="path of the built step_latency bench")
    parser.add_argument("--task", default=TASK)
    parser.add_argument("--profile", choices=("engine", "native"))
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--addr", help=argparse.SUPPRESS)
    ns = parser.parse_args()
    if ns.worker:
        ns.envs = int(ns.envs)
        print(json.dumps(worker(ns)))
        return

    import tamrm

    env_counts = [int(x) for x in ns.envs.split(",")]
    clients = [c for c in ns.clients.split(",") if c]
    with tempfile.TemporaryDirectory() as tmp, _server(ns.server) as addr:
        with tamrm.Client(addr) as admin:
            admin.create_task(ns.task, **task_config())
            if admin.get_task(ns.task).stats.pool_size == 0:
                seed_pool(admin, ns.task)
        if ns.profile:
            ns.envs = env_counts[0]
            profile(ns, addr)
            return
        old = old_client_dir(Path(tmp)) if any(c.startswith("grpcio") for c in clients) else None
        rust = rust_bench_path(ns.rust_bench) if "rust" in clients else None
        load = [os.getloadavg()]
        started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        results: dict[tuple[str, int], list[dict[str, Any]]] = {}
        for r in range(ns.rounds):
            for n in env_counts:
                order = clients[r % len(clients) :] + clients[: r % len(clients)]
                for name in order:
                    res = run_client(name, n, ns, addr, old, rust)
                    if res is not None:
                        results.setdefault((name, n), []).append(res)
                        print(
                            f"round {r + 1} {name:12s} {n:3d} envs: p50 {res['p50_us']:8.1f} µs"
                            f"  p99 {res['p99_us']:8.1f} µs",
                            file=sys.stderr,
                        )
            load.append(os.getloadavg())
    print(
        f"\n{started}; {platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; {ns.rounds} rounds x {ns.steps} timed steps "
        f"(+{ns.warmup} warm-up) per client and N; load average (1 min) during the run: "
        f"{min(x[0] for x in load):.1f}-{max(x[0] for x in load):.1f}\n"
    )
    print(
        "| client | envs | p50 (µs) | p50 range over rounds | p99 (µs) | p50 / Rust | p99 / Rust "
        "| p50 / Engine |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for n in env_counts:
        ref = results.get(("rust", n))
        engine = results.get(("engine", n))
        for name in clients:
            runs = results.get((name, n))
            if not runs:
                continue
            p50 = statistics.median(x["p50_us"] for x in runs)
            p99 = statistics.median(x["p99_us"] for x in runs)
            lo, hi = min(x["p50_us"] for x in runs), max(x["p50_us"] for x in runs)
            if ref and len(ref) == len(runs):
                r50 = statistics.median(
                    a["p50_us"] / b["p50_us"] for a, b in zip(runs, ref, strict=True)
                )
                r99 = statistics.median(
                    a["p99_us"] / b["p99_us"] for a, b in zip(runs, ref, strict=True)
                )
                ratios = f"{r50:.2f}x | {r99:.2f}x"
            else:
                ratios = "— | —"
            if engine and len(engine) == len(runs):
                e50 = statistics.median(
                    a["p50_us"] / b["p50_us"] for a, b in zip(runs, engine, strict=True)
                )
                ratios += f" | {e50:.2f}x"
            else:
                ratios += " | —"
            label = LABELS[name]
            if name == "aio" and runs[0].get("aio_transport"):
                label += f" [{runs[0]['aio_transport']}]"
            print(f"| {label} | {n} | {p50:.1f} | {lo:.1f}-{hi:.1f} | {p99:.1f} | {ratios} |")
    knn = {f"{k[0]}/{k[1]}": round(v[0].get("knn_active", 1.0), 3) for k, v in results.items()}
    print(f"\nkNN-active fraction of the timed entries: {knn}")


class _server:
    """A local in-memory server's address, or the given one."""

    def __init__(self, address: str | None) -> None:
        self.address = address
        self._cm: Any = None

    def __enter__(self) -> str:
        if self.address:
            return self.address
        import tamrm

        self._cm = tamrm.local_server(in_memory=True)
        return str(self._cm.__enter__().address)

    def __exit__(self, *exc: object) -> None:
        if self._cm is not None:
            self._cm.__exit__(*exc)


if __name__ == "__main__":
    main()
