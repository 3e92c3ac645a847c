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
    assert "ShapedVecEnv + bind_model (--data-dir)" in out
    assert "shaped + value_fn (in-memory)" in out
