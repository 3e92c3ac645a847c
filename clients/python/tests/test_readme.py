"""The Python snippets of the README and of docs/python.md's quickstart each run when
pasted alone."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO_ROOT

import tamrm


def _snippets(path: str, heading: str) -> list[str]:
    text = (REPO_ROOT / path).read_text()
    section = text[text.index(f"## {heading}\n") :]
    section = section[: section.index("\n## ", 1)]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def python_snippets() -> list[str]:
    """The README's two: an Engine shaping a gymnasium loop, a Client of a server."""
    return _snippets("README.md", "Python")


def sb3_snippet() -> str:
    """docs/python.md's Stable-Baselines3 quickstart."""
    found = [s for s in _snippets("docs/python.md", "Quickstart (fresh machine)") if "sb3" in s]
    assert len(found) == 1, found
    return found[0]


def test_readme_has_the_snippets() -> None:
    snippets = python_snippets()
    assert len(snippets) == 2
    assert "tamrm.gym.ShapedReward" in snippets[0] and "tamrm.Engine(" in snippets[0]
    assert "tamrm.Client()" in snippets[1]
    assert "tamrm.sb3.ShapedVecEnv" in sb3_snippet() and "tamrm.Engine(" in sb3_snippet()


def _run(
    code: str, cwd: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
        env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
        check=False,
    )


def test_readme_gymnasium_snippet_runs_alone_without_a_server(tmp_path: Path) -> None:
    # Pasted into a fresh directory: no server, pools in ./tamrm-data.
    proc = _run(python_snippets()[0], tmp_path, {"TAMRM_ADDRESS": "127.0.0.1:9"})
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    with tamrm.Engine(tmp_path / "tamrm-data") as engine:
        stats = engine.get_task("cartpole").stats
        assert stats.steps_shaped == 500
        assert stats.episodes_completed > 0 and stats.pool_size > 0


def test_guide_sb3_snippet_runs_alone_without_a_server(tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3")
    code = sb3_snippet()
    # Shorter training, still long enough for SB3 to print its table once.
    assert "model.learn(50_000," in code
    code = code.replace("model.learn(50_000,", "model.learn(4_000,")
    proc = _run(code, tmp_path, {"TAMRM_ADDRESS": "127.0.0.1:9"})
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "ep_rew_mean" in proc.stdout  # the run shows its progress
    assert "knn_active_frac" in proc.stdout  # and the shaped parts (SB3 groups by "tamrm/")


def test_readme_server_snippet_runs_alone(server_binary: str, tmp_path: Path) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        proc = _run(python_snippets()[1], tmp_path, {"TAMRM_ADDRESS": srv.address})
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
        with tamrm.Client(srv.address) as client:
            stats = client.get_task("cartpole").stats
            assert (stats.steps_shaped, stats.episodes_completed) == (2, 1)
            assert stats.open_streams == 0  # the snippet closed its session


def test_gitignore_has_the_data_dir() -> None:
    lines = (REPO_ROOT / ".gitignore").read_text().splitlines()
    assert "tamrm-data/" in lines
