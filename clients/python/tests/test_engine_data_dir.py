"""A data dir written by ``tamrm.Engine`` opens in ``tamrm serve`` and back; one holder
at a time (its LOCK)."""

from __future__ import annotations

import gc
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from reference import assert_pools_identical, assert_tasks_identical

import tamrm

TASKS: dict[str, dict[str, Any]] = {
    "maze/discrete": dict(num_actions=3, pool_capacity=4, k=2, start_step=1, min_pool_size=2),
    "arm/continuous": dict(action_dim=2, pool_capacity=3, start_step=0, min_pool_size=1),
}


def shape_episodes(backend: tamrm.Engine | tamrm.Client, seed: int, batches: int = 40) -> list[Any]:
    """Shape random episodes on every task of ``TASKS``; return every answer."""
    rng = np.random.default_rng(seed)
    answers = []
    for task_id, config in TASKS.items():
        with backend.session(task_id, 2) as s:
            for _ in range(batches):
                if "num_actions" in config:
                    actions = rng.integers(0, 3, 2)
                else:
                    actions = rng.integers(-1, 2, (2, 2)) * 0.5
                ends = rng.random(2) < 0.2
                r = s.step(
                    actions,
                    rng.normal(size=2) / 3,
                    terminated=ends,
                    values=rng.normal(size=2),
                    next_values=rng.normal(size=2),
                )
                answers.append(r)
    return answers


def snapshot(backend: tamrm.Engine | tamrm.Client) -> dict[str, tuple[tamrm.Pool, tamrm.Task]]:
    return {t: (backend.get_pool(t), backend.get_task(t)) for t in TASKS}


def assert_same_state(got: dict[str, Any], want: dict[str, Any]) -> None:
    assert list(got) == list(want)
    for task_id in want:
        assert_pools_identical(got[task_id][0], want[task_id][0])
        assert_tasks_identical(got[task_id][1], want[task_id][1])


def test_engine_data_dir_opens_in_the_server_and_back(tmp_path: Path, server_binary: str) -> None:
    data = tmp_path / "data"
    engine = tamrm.Engine(data)
    for task_id, config in TASKS.items():
        engine.create_task(task_id, **config)
    engine.add_trajectory("maze/discrete", [0, 1, 2, 2], 3.5)
    shape_episodes(engine, seed=1)
    written = snapshot(engine)
    assert all(pool.pool_version >= 3 for pool, _ in written.values()), written
    assert all(task.stats.episodes_completed > 3 for _, task in written.values()), written
    engine.close()
    del engine  # the last reference: the engine and its LOCK are released
    gc.collect()

    with (
        tamrm.local_server(binary=server_binary, data_dir=data) as srv,
        tamrm.Client(srv.address) as client,
    ):
        assert srv.data_dir == data
        assert sorted(t.task_id for t in client.list_tasks()) == sorted(TASKS)
        assert_same_state(snapshot(client), written)
        # The server goes on from the engine's pools: more episodes change them.
        shape_episodes(client, seed=2)
        served = snapshot(client)
        for task_id in TASKS:
            assert served[task_id][0].pool_version > written[task_id][0].pool_version
    # Stopped (SIGTERM: a graceful shutdown). A copy of the data dir, so that an engine
    # and a server can each open one and shape the same steps side by side.
    twin = tmp_path / "twin"
    shutil.copytree(data, twin)
    engine = tamrm.Engine(data)
    assert_same_state(snapshot(engine), served)
    with (
        tamrm.local_server(binary=server_binary, data_dir=twin) as srv,
        tamrm.Client(srv.address) as client,
    ):
        assert_same_state(snapshot(client), served)
        from_engine = shape_episodes(engine, seed=3)
        from_server = shape_episodes(client, seed=3)
        assert len(from_engine) == len(from_server) > 0
        assert any(r.knn_active.any() for r in from_engine)
        for a, b in zip(from_engine, from_server, strict=True):
            for name in ("rewards", "knn_rewards", "potentials", "steps", "knn_active"):
                assert np.array_equal(getattr(a, name), getattr(b, name)), name
            assert a.pool_version == b.pool_version
        assert_same_state(snapshot(engine), snapshot(client))
    engine.close()
    del engine  # the last reference: the engine and its LOCK are released
    gc.collect()


_OPEN_ENGINE = """
import sys, tamrm
try:
    engine = tamrm.Engine(sys.argv[1])
except tamrm.FailedPrecondition as exc:
    print(exc.details)
    sys.exit(3)
pool = engine.get_pool(sys.argv[2])
print(pool.pool_version, len(pool))
"""


def open_in_subprocess(data: Path, task_id: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _OPEN_ENGINE, str(data), task_id],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )


def test_a_data_dir_held_by_an_engine_is_refused(tmp_path: Path, server_binary: str) -> None:
    data = tmp_path / "data"
    engine = tamrm.Engine(data)
    engine.create_task("maze/discrete", **TASKS["maze/discrete"])
    engine.create_task("arm/continuous", **TASKS["arm/continuous"])
    session = engine.session("maze/discrete", 2)
    session.step([0, 1], [1.0, 2.0], [True, False])
    before = engine.get_pool("maze/discrete")
    assert before.pool_version == 1

    other = open_in_subprocess(data, "maze/discrete")
    assert other.returncode == 3, (other.stdout, other.stderr)
    message = other.stdout
    assert "LOCK" in message and "in use" in message and str(data) in message, message
    # In this process too.
    with pytest.raises(tamrm.FailedPrecondition, match="in use"):
        tamrm.Engine(data)
    with pytest.raises(tamrm.ServerStartError, match="LOCK"):
        with tamrm.local_server(binary=server_binary, data_dir=data, startup_timeout=30):
            pass

    # Nothing changed, and the holder goes on.
    assert_pools_identical(engine.get_pool("maze/discrete"), before)
    result = session.step([1, 1], [1.0, 1.0], [False, True])
    assert result.pool_version == 2
    after = engine.get_pool("maze/discrete")
    session.close()
    del session
    engine.close()
    del engine  # the last reference: the engine and its LOCK are released
    gc.collect()

    # Released: another process opens it and sees the pool as the engine left it.
    reopened = open_in_subprocess(data, "maze/discrete")
    assert reopened.returncode == 0, (reopened.stdout, reopened.stderr)
    assert reopened.stdout.split() == [str(after.pool_version), str(len(after))]


def test_a_data_dir_held_by_a_server_is_refused(tmp_path: Path, server_binary: str) -> None:
    data = tmp_path / "data"
    with (
        tamrm.local_server(binary=server_binary, data_dir=data) as srv,
        tamrm.Client(srv.address) as client,
    ):
        client.create_task("maze/discrete", **TASKS["maze/discrete"])
        client.add_trajectory("maze/discrete", [2, 2, 1], 4.0)
        before = client.get_pool("maze/discrete")
        with pytest.raises(tamrm.FailedPrecondition) as info:
            tamrm.Engine(data)
        assert "LOCK" in info.value.details and "in use" in info.value.details
        other = open_in_subprocess(data, "maze/discrete")
        assert other.returncode == 3 and "LOCK" in other.stdout, (other.stdout, other.stderr)
        assert_pools_identical(client.get_pool("maze/discrete"), before)
    engine = tamrm.Engine(data)
    assert_pools_identical(engine.get_pool("maze/discrete"), before)
    engine.close()
    del engine  # the last reference: the engine and its LOCK are released
    gc.collect()
