"""Fixtures: one real ``tamrm`` server per test session, unique task ids per test."""

from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

import tamrm

# No per-example deadline (CI machines are small and shared); derandomized in CI so that a
# run is reproducible.
settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")

REPO_ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="session", autouse=True)
def _sb3_log_dir(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One SB3 log dir for the whole run: without one, every learn() makes its own."""
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3-logs")))


def _binary() -> str:
    env = os.environ.get("TAMRM_BIN")
    if env:
        return env
    return str(tamrm.find_binary())


@pytest.fixture(scope="session")
def server_binary() -> str:
    return _binary()


@pytest.fixture(scope="session")
def server(server_binary: str) -> Iterator[tamrm.LocalServer]:
    with tamrm.local_server(binary=server_binary) as srv:
        yield srv


@pytest.fixture(scope="session")
def remote_client(server: tamrm.LocalServer) -> Iterator[tamrm.Client]:
    with tamrm.Client(server.address) as c:
        yield c


@pytest.fixture(scope="session")
def engine() -> Iterator[tamrm.Engine]:
    with tamrm.Engine() as e:
        yield e


@pytest.fixture(params=["remote", "engine"])
def client(request: pytest.FixtureRequest) -> tamrm.Client:
    """Every test written against a client runs twice: on a real server through
    ``tamrm.Client``, and in-process on ``tamrm.Engine`` (same methods, same answers)."""
    if request.param == "engine":
        return request.getfixturevalue("engine")  # type: ignore[no-any-return]
    return request.getfixturevalue("remote_client")  # type: ignore[no-any-return]


@pytest.fixture
def task_id(request: pytest.FixtureRequest) -> str:
    name = re.sub(r"[^A-Za-z0-9._-]", "-", request.node.name)[:80]
    return f"t/{name}/{uuid.uuid4().hex[:8]}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def redis_url(tmp_path: Path) -> Iterator[str]:
    """A ``redis-server`` of the test's own on a free port (durable: every write synced),
    for replicas sharing a store; tests using it skip when it is not installed."""
    port = _free_port()
    durable = ["--appendonly", "yes", "--appendfsync", "always", "--save", ""]
    proc = subprocess.Popen(
        [
            "redis-server",
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--dir",
            str(tmp_path),
            *durable,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 20
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port)) as s:
                s.sendall(b"PING\r\n")
                if s.recv(16).startswith(b"+PONG"):
                    break
            assert time.monotonic() < deadline, "redis-server did not answer"
            time.sleep(0.02)
        yield f"redis://127.0.0.1:{port}"
    finally:
        proc.kill()
        proc.wait()
