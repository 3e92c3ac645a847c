"""Messages a newcomer meets: the missing sb3 extra, a wrong --server."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import tamrm

CLIENT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("missing", ["stable_baselines3", "torch"])
def test_import_sb3_without_the_extra_names_it(
    monkeypatch: pytest.MonkeyPatch, missing: str
) -> None:
    # Simulate an install without the extra: the module cannot be imported.
    before = set(sys.modules)
    monkeypatch.setitem(sys.modules, missing, None)
    for name in [
        m for m in sys.modules if m == "stable_baselines3" or m.startswith("stable_baselines3.")
    ]:
        if name != missing:
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.delitem(sys.modules, "tamrm.sb3", raising=False)
    monkeypatch.delitem(tamrm.__dict__, "sb3", raising=False)
    with pytest.raises(ImportError, match=r"pip install 'tamrm\[sb3\]'") as info:
        importlib.import_module("tamrm.sb3")
    assert not isinstance(info.value, ModuleNotFoundError) or info.value.name == missing
    assert info.value.__cause__ is None
    with pytest.raises(ImportError, match=r"tamrm\[sb3\]"):
        _ = tamrm.sb3  # the lazy attribute too
    # Drop whatever the failed imports left behind; monkeypatch restores the rest.
    for name in set(sys.modules) - before:
        del sys.modules[name]


@pytest.mark.parametrize(
    ("server", "says"),
    [("WRONG", "expected host:port"), ("127.0.0.1:1", "no tamrm server at 127.0.0.1:1")],
)
def test_cartpole_wrong_server_fails_fast(server_binary: str, server: str, says: str) -> None:
    pytest.importorskip("stable_baselines3")
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, str(CLIENT / "examples" / "cartpole.py"), "--server", server],
        capture_output=True,
        text=True,
        env=dict(os.environ, TAMRM_BIN=server_binary),
        timeout=300,
        check=False,
    )
    elapsed = time.monotonic() - started
    assert proc.returncode != 0
    assert says in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "A2C" not in proc.stdout  # no training run before the check
    assert elapsed < 60, elapsed
