"""What the installed package is: one version, and the server's own command line.

Installed from the wheel (CI installs it into a fresh venv without a Rust toolchain), the
package holds the server binary as the ``tamrm`` command; the tests marked ``wheel`` need
that and are skipped, saying so, in a source install.
"""

from __future__ import annotations

import importlib.metadata
import os
import re
import signal
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import pytest

import tamrm
from tamrm._server import installed_binary

REPO_ROOT = Path(__file__).resolve().parents[3]

wheel = pytest.mark.skipif(
    installed_binary() is None,
    reason="a source install: the package holds no server binary (the wheel does)",
)


def workspace_version() -> str:
    text = (REPO_ROOT / "Cargo.toml").read_text()
    found = re.search(r'^\[workspace\.package\]\n(?:[^\[].*\n)*?version = "([^"]+)"', text, re.M)
    assert found, "no version in [workspace.package] of Cargo.toml"
    return found.group(1)


def test_the_package_has_the_workspace_version() -> None:
    assert tamrm.__version__ == workspace_version()
    assert importlib.metadata.version("tamrm") == tamrm.__version__


def run(argv: list[str | Path]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)


@wheel
def test_the_tamrm_command_is_the_server_binary() -> None:
    binary = installed_binary()
    assert binary is not None
    command = Path(sysconfig.get_path("scripts")) / "tamrm"
    assert command.resolve() == binary
    out = run([binary, "--version"])
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"tamrm {tamrm.__version__} (commit "), out.stdout
    # The binary is static: no loader, no libc of the machine's needed.
    assert b"ld-linux" not in binary.read_bytes()[:65536]


@wheel
def test_python_m_tamrm_is_the_same_command_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TAMRM_BIN", raising=False)
    binary = installed_binary()
    assert binary is not None and tamrm.find_binary() == binary
    for args in (["--version"], ["serve", "--no-such-flag"], ["key", "--help"]):
        direct = run([binary, *args])
        module = run([sys.executable, "-m", "tamrm", *args])
        assert (module.returncode, module.stdout, module.stderr) == (
            direct.returncode,
            direct.stdout,
            direct.stderr,
        ), args
    assert run([binary, "serve", "--no-such-flag"]).returncode == 2


def serve(argv: list[str | Path], data: Path, port_file: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*argv, "serve", "--listen", "127.0.0.1:0", "--data-dir", data, "--port-file", port_file],
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_port(port_file: Path, proc: subprocess.Popen[str]) -> str:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if port_file.exists() and port_file.read_text().endswith("\n"):
            return port_file.read_text().strip()
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        time.sleep(0.05)
    raise AssertionError("the server wrote no port file")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_python_m_tamrm_stops_on_a_signal_as_the_binary_does(
    sig: signal.Signals, tmp_path: Path, server_binary: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A server started from Python stops gracefully, keeping what it acknowledged."""
    monkeypatch.setenv("TAMRM_BIN", server_binary)
    outcomes = []
    for name, argv in (("binary", [server_binary]), ("module", [sys.executable, "-m", "tamrm"])):
        data, port_file = tmp_path / name, tmp_path / f"{name}.port"
        proc = serve(argv, data, port_file)
        try:
            address = wait_port(port_file, proc)
            with tamrm.Client(address) as client:
                client.create_task("t", num_actions=3, pool_capacity=4, k=1)
                client.add_trajectory("t", [0, 1, 2], 1.0)
            os.kill(proc.pid, sig)
            _, log = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert "stopped" in log.splitlines()[-1], log
        # The pool survives the stop: a server on the same data dir has it.
        port_file.unlink()
        again = serve([server_binary], data, port_file)
        try:
            with tamrm.Client(wait_port(port_file, again)) as client:
                version = client.get_task("t").stats.pool_version
        finally:
            again.terminate()
            again.wait(timeout=30)
        outcomes.append((proc.returncode, version))
    assert outcomes[0] == outcomes[1] == (0, 1)
