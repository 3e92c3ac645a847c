"""The README's Python snippets each run when pasted alone (issue 15, item 9)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from conftest import REPO_ROOT

import tamrm


def python_snippets() -> list[str]:
    text = (REPO_ROOT / "README.md").read_text()
    section = text[text.index("## Python\n") :]
    section = section[: section.index("\n## ", 1)]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_has_the_snippets() -> None:
    snippets = python_snippets()
    assert len(snippets) == 2
    assert "tamrm.gym.ShapedReward" in snippets[0]
    assert "tamrm.sb3.ShapedVecEnv" in snippets[1]


@pytest.mark.parametrize("index", [0, 1], ids=["gymnasium", "sb3"])
def test_readme_snippet_runs_alone(server_binary: str, index: int) -> None:
    code = python_snippets()[index]
    if index == 1:
        pytest.importorskip("stable_baselines3")
        # Shorter training, still long enough for SB3 to print its table once.
        assert "model.learn(50_000)" in code
        code = code.replace("model.learn(50_000)", "model.learn(4_000)")
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        proc = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=REPO_ROOT,
            env={**os.environ, "TAMRM_ADDRESS": srv.address, "OMP_NUM_THREADS": "1"},
            check=False,
        )
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
        with tamrm.Client(srv.address) as client:
            stats = client.get_task("cartpole").stats
            assert stats.steps_shaped > 0
            assert stats.open_streams == 0  # the snippet closed its session
    if index == 1:
        assert "ep_rew_mean" in proc.stdout  # the run shows its progress


def test_gitignore_has_the_data_dir() -> None:
    lines = (REPO_ROOT / ".gitignore").read_text().splitlines()
    assert "tamrm-data/" in lines
