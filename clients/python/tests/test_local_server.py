"""local_server(): binary discovery, health, data dir persistence, shutdown."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import tamrm
from tamrm._server import health_check


def test_health_services(server: tamrm.LocalServer) -> None:
    assert health_check(server.address, "")
    assert health_check(server.address, "tamrm.v1.Shaping")
    assert not health_check(server.address, "no.such.Service")
    assert server.port > 0 and server.address.startswith("127.0.0.1:")
    assert server.process.poll() is None


def test_find_binary_env(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, server_binary: str
) -> None:
    monkeypatch.setenv("TAMRM_BIN", server_binary)
    assert tamrm.find_binary() == Path(server_binary).resolve()
    monkeypatch.setenv("TAMRM_BIN", str(tmp_path / "missing"))
    with pytest.raises(tamrm.ServerStartError, match="TAMRM_BIN"):
        tamrm.find_binary()


def test_start_failure_reports_log(tmp_path: Path) -> None:
    fake = tmp_path / "tamrm"
    fake.write_text("#!/bin/sh\necho 'boom: cannot start' >&2\nexit 3\n")
    fake.chmod(0o755)
    with (
        pytest.raises(tamrm.ServerStartError, match="boom") as err,
        tamrm.local_server(binary=fake),
    ):
        pass
    assert "exited with code 3" in str(err.value)


def test_data_dir_survives_restart(tmp_path: Path, server_binary: str) -> None:
    data = tmp_path / "data"
    with tamrm.local_server(binary=server_binary, data_dir=data) as srv, srv.client() as c:
        c.create_task("kept", num_actions=2, pool_capacity=2)
        c.add_trajectory("kept", [0, 1], 1.0)
        c.reset_pool("kept")
        c.add_trajectory("kept", [1, 1, 0], 2.5)
        version = c.get_task("kept").stats.pool_version
        process = srv.process
    assert process.returncode is not None  # stopped on exit
    with tamrm.local_server(binary=server_binary, data_dir=data) as srv, srv.client() as c:
        task = c.get_task("kept")
        assert task.config.pool_capacity == 2
        assert task.stats.pool_version >= version
        pool = c.get_pool("kept")
        assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [([1, 1, 0], 2.5)]
    assert os.listdir(data)


def test_server_shutdown_surfaces_as_unavailable(server_binary: str) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv, srv.client() as c:
        assert srv.data_dir is None
        c.create_task("x", num_actions=2)
        session = c.session("x", 1)
        session.step([0], [1.0])
        srv.process.terminate()  # graceful: open streams end after their current batch
        assert srv.process.wait(30) == 0
        with pytest.raises(tamrm.Unavailable):
            session.step([0], [1.0])
        assert session.closed
        with pytest.raises(tamrm.Unavailable):
            c.get_task("x")
