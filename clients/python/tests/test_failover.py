"""Replicas sharing one Redis store (SPEC §9, §10): ``tamrm.Client`` given
several addresses goes on through another replica when the one it uses is killed with -9,
with the rewards an uninterrupted stream would have had.

The tests start their own ``redis-server`` on a free port (skipped when it is not
installed; ``.ci/run`` installs it)."""

from __future__ import annotations

import contextlib
import shutil
import signal
import socket
import time

import numpy as np
import pytest

import tamrm

NUM_ENVS = 3
CONFIG = {"num_actions": 3, "pool_capacity": 4, "k": 2, "start_step": 1, "min_pool_size": 1}

pytestmark = pytest.mark.skipif(
    shutil.which("redis-server") is None, reason="redis-server is not installed"
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _replica(binary: str, url: str) -> contextlib.AbstractContextManager[tamrm.LocalServer]:
    return tamrm.local_server(
        binary=binary, in_memory=True, args=["--store", url, "--store-poll-ms", "200"]
    )


def _batches(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [
        (rng.integers(0, 3, NUM_ENVS), rng.normal(size=NUM_ENVS), rng.random(NUM_ENVS) < 0.2)
        for _ in range(n)
    ]


def _shape(session: tamrm.Session, batches: list) -> list[list[float]]:
    return [session.step(a, r, t).rewards.tolist() for a, r, t in batches]


def _uninterrupted(batches: list) -> list[list[float]]:
    with tamrm.Engine() as engine:
        engine.create_task("t", **CONFIG)
        with engine.session("t", num_envs=NUM_ENVS) as s:
            return _shape(s, batches)


def test_a_session_goes_on_through_another_replica_after_kill_9(
    server_binary: str, redis_url: str
) -> None:
    batches = _batches(3, 60)
    want = _uninterrupted(batches)
    with _replica(server_binary, redis_url) as a, _replica(server_binary, redis_url) as b:
        client = tamrm.Client([a.address, b.address], resume_timeout_secs=30)
        assert client.targets == (a.address, b.address)
        client.create_task("t", **CONFIG)
        session = client.session("t", num_envs=NUM_ENVS)
        got = _shape(session, batches[:25])
        a.process.send_signal(signal.SIGKILL)
        a.process.wait()
        started = time.monotonic()
        got += _shape(session, batches[25:])
        assert time.monotonic() - started < 20
        assert got == want
        # Unary calls go to the replica that answers, with the store's pool.
        pool = client.get_pool("t")
        assert pool.pool_version == client.get_task("t").stats.pool_version
        session.close()
        client.close()


def test_unary_calls_skip_a_replica_that_is_down(server_binary: str, redis_url: str) -> None:
    dead = f"127.0.0.1:{_free_port()}"
    with _replica(server_binary, redis_url) as a, _replica(server_binary, redis_url) as b:
        # A task created through one replica is there at once on the other.
        tamrm.Client(b.address).create_task("t", **CONFIG)
        client = tamrm.Client([dead, a.address])
        assert client.get_task("t").config.num_actions == 3
        added = client.add_trajectory("t", [0, 1, 2], 5.0)
        assert added.inserted
        assert tamrm.Client(b.address).get_pool("t").pool_version >= 0
        with client.session("t", num_envs=1) as s:
            s.step([1], [1.0], [True])
        client.close()


def test_every_replica_down_is_unavailable_naming_them(server_binary: str) -> None:
    dead = [f"127.0.0.1:{_free_port()}", f"127.0.0.1:{_free_port()}"]
    client = tamrm.Client(dead, timeout=5)
    with pytest.raises(tamrm.Unavailable) as err:
        client.get_task("t")
    for address in dead:
        assert address in str(err.value)
    client.close()


def test_targets_are_checked_and_pickled() -> None:
    with pytest.raises(ValueError, match="empty"):
        tamrm.Client([])
    with pytest.raises(ValueError, match="no port"):
        tamrm.Client(["127.0.0.1:5", "nohost"])
    import pickle

    c = tamrm.Client(["127.0.0.1:5", "127.0.0.1:6"])
    clone = pickle.loads(pickle.dumps(c))
    assert clone.targets == c.targets
    assert "targets=" in repr(c)


def test_the_address_variable_may_name_several(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TAMRM_ADDRESS", "127.0.0.1:5, 127.0.0.1:6")
    assert tamrm.Client().targets == ("127.0.0.1:5", "127.0.0.1:6")
