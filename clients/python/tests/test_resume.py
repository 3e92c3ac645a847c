"""Transparent resume (SPEC §9): a session whose server is killed and
restarted with the same data dir goes on as if nothing had happened, with the rewards an
uninterrupted stream would have had."""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import tamrm

NUM_ENVS = 3
CONFIG = {"num_actions": 3, "pool_capacity": 4, "k": 2, "start_step": 1, "min_pool_size": 1}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _batches(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        actions = rng.integers(0, 3, NUM_ENVS)
        rewards = rng.normal(size=NUM_ENVS)
        terminated = rng.random(NUM_ENVS) < 0.2
        out.append((actions, rewards, terminated))
    return out


def _shape_all(session: tamrm.Session, batches: list, start: int, stop: int) -> list:
    return [session.step(a, r, t).rewards.tolist() for a, r, t in batches[start:stop]]


def test_a_session_resumes_across_a_kill_and_restart(server_binary: str, tmp_path: Path) -> None:
    batches = _batches(7, 40)
    # The reference: one uninterrupted stream.
    with tamrm.Engine() as engine:
        engine.create_task("t", **CONFIG)
        with engine.session("t", num_envs=NUM_ENVS) as s:
            want = _shape_all(s, batches, 0, len(batches))

    port = _free_port()
    listen = f"127.0.0.1:{port}"
    data = tmp_path / "data"
    with tamrm.local_server(binary=server_binary, data_dir=data, listen=listen) as first:
        client = tamrm.Client(first.address, resume_timeout_secs=30)
        client.create_task("t", **CONFIG)
        session = client.session("t", num_envs=NUM_ENVS)
        got = _shape_all(session, batches, 0, 15)
        first.process.send_signal(signal.SIGKILL)
        first.process.wait()

        # The next step blocks until a server is back on the same address and data dir.
        restarted: list = []

        def restart() -> None:
            time.sleep(0.5)
            cm = tamrm.local_server(binary=server_binary, data_dir=data, listen=listen)
            restarted.append((cm, cm.__enter__()))

        t = threading.Thread(target=restart)
        t.start()
        try:
            got += _shape_all(session, batches, 15, len(batches))
        finally:
            t.join()
            for cm, _ in restarted:
                cm.__exit__(None, None, None)
        session.close()
        client.close()
    assert got == want


def test_without_a_server_the_step_gives_up_after_its_deadline(server_binary: str) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        client = tamrm.Client(srv.address, resume_timeout_secs=1.0)
        client.create_task("t", **CONFIG)
        session = client.session("t", num_envs=NUM_ENVS)
        a, r, t = _batches(1, 1)[0]
        session.step(a, r, np.zeros(NUM_ENVS, bool))
        srv.process.send_signal(signal.SIGKILL)
        srv.process.wait()
        started = time.monotonic()
        with pytest.raises(tamrm.Unavailable, match="resume_timeout_secs"):
            session.step(a, r, t)
        assert time.monotonic() - started < 20
        with pytest.raises(tamrm.SessionClosed):
            session.step(a, r, t)
        client.close()


def test_resume_can_be_switched_off(server_binary: str) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        client = tamrm.Client(srv.address, resume_timeout_secs=None)
        client.create_task("t", **CONFIG)
        session = client.session("t", num_envs=NUM_ENVS)
        srv.process.send_signal(signal.SIGKILL)
        srv.process.wait()
        a, r, t = _batches(1, 1)[0]
        started = time.monotonic()
        with pytest.raises(tamrm.Unavailable):
            session.step(a, r, t)
        assert time.monotonic() - started < 10
        client.close()
