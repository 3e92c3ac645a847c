"""The example and the benchmark script run (small budgets; no timing asserted)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

CLIENT = Path(__file__).resolve().parents[1]

pytest.importorskip("stable_baselines3")


def _run(args: list[str], server_binary: str) -> str:
    env = dict(os.environ, TAMRM_BIN=server_binary)
    proc = subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, env=env, timeout=600, check=False
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def test_cartpole_example_quick(server_binary: str) -> None:
    out = _run(
        [str(CLIENT / "examples" / "cartpole.py"), "--quick", "--n-envs", "4"], server_binary
    )
    lines = out.strip().splitlines()
    assert any(line.startswith("A2C ") for line in lines), out
    assert any(line.startswith("A2C + tamrm") for line in lines), out
    assert "episodes" in out


def test_cleanrl_ppo_example_quick(server_binary: str) -> None:
    out = _run([str(CLIENT / "examples" / "cleanrl_ppo.py"), "--quick"], server_binary)
    if "tensorboard not installed" in out:  # else the scalars go to runs/
        lines = [line for line in out.splitlines() if line.startswith("step ")]
        assert len(lines) == 3, out  # one line per update
        for key in ("shaping/R=", "shaping/alpha_r=", "shaping/beta_F=", "shaping/pool_size="):
            assert key in lines[-1], out
    assert "episodes, last-20 mean return" in out


def test_sb3_dqn_example_quick(server_binary: str) -> None:
    out = _run([str(CLIENT / "examples" / "sb3_dqn.py"), "--quick"], server_binary)
    assert "Q(s0, .) = [" in out, out
    assert "(unshaped, pool untouched)" in out, out


def test_pettingzoo_sb3_example_quick(server_binary: str) -> None:
    pytest.importorskip("supersuit")
    pytest.importorskip("mpe2")
    script = str(CLIENT / "examples" / "pettingzoo_sb3.py")
    # One pool for the three agents, SuperSuit's copies in this process.
    out = _run([script, "--quick"], server_binary)
    assert "3 agents sharing one policy, 2 env copies, shared pool" in out, out
    (task,) = [line for line in out.splitlines() if line.startswith("task ")]
    assert " 1152 steps shaped" in task, out  # every agent-step of 3 PPO updates
    # A pool per agent, SuperSuit's copies in two worker processes (the wrapper pickled).
    out = _run([script, "--quick", "--layout", "per-agent", "--num-cpus", "2"], server_binary)
    tasks = [line for line in out.splitlines() if line.startswith("task ")]
    assert [t.split()[1].rsplit("/", 1)[1] for t in tasks] == ["agent_0:", "agent_1:", "agent_2:"]
    assert all(" 384 steps shaped" in t for t in tasks), out


def _table_rows(out: str) -> dict[str, str]:
    """The rows of the markdown tables in ``out``, by their first cell."""
    return {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ")}


def test_overhead_benchmark_smoke(server_binary: str) -> None:
    out = _run(
        [
            str(CLIENT / "benchmarks" / "overhead.py"),
            "--repeats",
            "1",
            "--steps",
            "50",
            "--num-envs",
            "4",
            "--a2c-envs",
            "2",
            "--a2c-timesteps",
            "200",
        ],
        server_binary,
    )
    assert "| workload | variant |" in out
    for variant in ("Engine, in memory", "Engine, data dir", "Client, server in memory"):
        assert variant in out
    assert "Client, server --data-dir" in out and "SB3 A2C" in out
    assert "floor: a TCP round trip to an echo" in out
    assert "Client(busy_poll_us=200), server in memory" in out
    assert "Client(busy_poll_us=200), server in memory, --worker-threads 1" in out
    assert "floor: a pass-through wrapper, no shaping" in out
    assert "Engine, in memory, no values bound" in out
    # The server "on another machine": a delaying proxy process between them.
    assert "Client session(local=True), server --data-dir, 1 ms each way" in out
    assert "Client, server --data-dir, 1 ms each way" in out
    assert "the learning thread off the CPU" in out
    assert "learning DIFFERED" not in out
    # With alpha = beta = 0 every backend's run learns what the plain run learns.
    assert "(same learning)" in out and "default weights" in out
    assert "DIFFERED" not in out, out


def test_episode_ends_benchmark_smoke(server_binary: str) -> None:
    out = _run(
        [
            str(CLIENT / "benchmarks" / "episode_ends.py"),
            "--rounds",
            "1",
            "--steps",
            "200",
            "--gap-us",
            "0",
        ],
        server_binary,
    )
    rows = _table_rows(out)
    assert set(rows) >= {"engine", "local", "local-dir", "local-shm"}, out
    for name in ("engine", "local", "local-dir", "local-shm"):
        cells = [float(c) for c in rows[name].split("|")[2:7]]
        assert all(c > 0 for c in cells), out


def test_round_trip_cpu_benchmark_smoke(server_binary: str) -> None:
    out = _run(
        [
            str(CLIENT / "benchmarks" / "round_trip_cpu.py"),
            "--rounds",
            "1",
            "--steps",
            "30",
            "--warmup",
            "5",
            "--gap-us",
            "100",
            "--server-args=--worker-threads=1",
        ],
        server_binary,
    )
    rows = _table_rows(out)
    assert set(rows) >= {"tcp", "remote", "engine"}, out
    # Every variant measured something; only the remote one has a server.
    cells = {name: [c.strip() for c in row.split("|")[2:6]] for name, row in rows.items()}
    for name in ("tcp", "remote", "engine"):
        assert all(float(c) > 0 for c in cells[name][:3]), out
    assert float(cells["remote"][3]) > 0 and cells["tcp"][3] == "—", out
    assert "['--worker-threads', '1']" in out
