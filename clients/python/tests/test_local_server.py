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
    # A broken stream is resumed for resume_timeout_secs before it raises: 1 s, not 60.
    with (
        tamrm.local_server(binary=server_binary, in_memory=True) as srv,
        srv.client(resume_timeout_secs=1.0) as c,
    ):
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


def test_a_one_thread_server_serves_concurrent_durable_sessions(
    tmp_path: Path, server_binary: str
) -> None:
    # --worker-threads 1: one runtime thread for every connection, with a data dir (so
    # commits go through the store's group-commit writer) and four sessions stepping at
    # once, each ending episodes. Nothing may wait for a second runtime thread.
    import numpy as np
    from streams import in_threads

    args = ["--worker-threads", "1"]
    with tamrm.local_server(binary=server_binary, data_dir=tmp_path / "d", args=args) as srv:
        assert "runtime threads: 1" in srv.log()
        with tamrm.Client(srv.address) as client:
            client.create_task("one-thread", num_actions=2, pool_capacity=5)

            def run(seed: int) -> None:
                rng = np.random.default_rng(seed)
                with client.session("one-thread", 3) as session:
                    for t in range(120):
                        ends = np.full(3, t % 20 == 19)
                        session.step(rng.integers(0, 2, size=3), np.ones(3), ends)

            in_threads(run, 4)
            stats = client.get_task("one-thread").stats
            assert stats.episodes_completed == 4 * 3 * 6
            assert len(client.get_pool("one-thread").trajectories) == 5
