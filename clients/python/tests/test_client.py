"""Every client call and error type, against the real server."""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest

import tamrm

DEFAULTS = {
    "pool_capacity": 20,
    "k": 20,
    "start_step": 10,
    "min_pool_size": 20,
    "alpha": 0.8,
    "beta": 0.8,
    "gamma": 0.99,
    "max_trajectory_len": 100000,
    "gate_potential": False,
    "require_score_spread": False,
}


def test_create_task_fills_defaults(client: tamrm.Client, task_id: str) -> None:
    task = client.create_task(task_id, num_actions=3)
    assert task.task_id == task_id
    assert task.config.num_actions == 3
    assert task.config.action_dim == 0
    assert task.config.discrete
    for name, value in DEFAULTS.items():
        assert getattr(task.config, name) == pytest.approx(value), name
    assert task.stats.pool_size == 0
    assert task.stats.min_length == 0
    assert task.stats.episodes_completed == 0
    assert task.stats.steps_shaped == 0


def test_create_task_default_k_and_min_pool_follow_capacity(
    client: tamrm.Client, task_id: str
) -> None:
    task = client.create_task(task_id, action_dim=2, pool_capacity=7)
    assert not task.config.discrete
    assert task.config.action_dim == 2
    assert task.config.k == 7
    assert task.config.min_pool_size == 7


def test_create_task_all_fields(client: tamrm.Client, task_id: str) -> None:
    kwargs = {
        "num_actions": 5,
        "pool_capacity": 9,
        "k": 3,
        "start_step": 0,
        "min_pool_size": 2,
        "alpha": 0.25,
        "beta": 0.0,
        "gamma": 1.0,
        "max_trajectory_len": 50,
        "gate_potential": True,
        "require_score_spread": True,
    }
    task = client.create_task(task_id, **kwargs)  # type: ignore[arg-type]
    for name, value in kwargs.items():
        assert getattr(task.config, name) == value, name
    # The keyword arguments are exactly the TaskConfig fields.
    assert set(tamrm.CONFIG_FIELDS) == {
        "num_actions",
        "action_dim",
        "pool_capacity",
        "k",
        "start_step",
        "min_pool_size",
        "alpha",
        "beta",
        "gamma",
        "max_trajectory_len",
        "gate_potential",
        "require_score_spread",
    }


def test_create_task_is_idempotent_and_conflicts(client: tamrm.Client, task_id: str) -> None:
    first = client.create_task(task_id, num_actions=2, pool_capacity=5)
    client.add_trajectory(task_id, [0, 1, 1], 3.0)
    # Same resolved config (explicit defaults included): returned unchanged, pool kept.
    again = client.create_task(task_id, num_actions=2, pool_capacity=5, k=5, alpha=0.8)
    assert again.config == first.config
    assert again.stats.pool_size == 1
    with pytest.raises(tamrm.AlreadyExists) as err:
        client.create_task(task_id, num_actions=2, pool_capacity=6)
    assert err.value.code is not None and err.value.code.name == "ALREADY_EXISTS"
    assert client.get_task(task_id).config.pool_capacity == 5


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"num_actions": 2, "action_dim": 2}, "num_actions"),
        ({}, "num_actions"),
        ({"num_actions": 2, "pool_capacity": 0}, "pool_capacity"),
        ({"num_actions": 2, "pool_capacity": 4, "k": 5}, "k"),
        ({"num_actions": 2, "k": 0}, "k"),
        ({"num_actions": 2, "pool_capacity": 4, "min_pool_size": 5}, "min_pool_size"),
        ({"num_actions": 2, "min_pool_size": 0}, "min_pool_size"),
        ({"num_actions": 2, "gamma": 1.5}, "gamma"),
        ({"num_actions": 2, "gamma": -0.1}, "gamma"),
        ({"num_actions": 2, "alpha": math.inf}, "alpha"),
        ({"num_actions": 2, "beta": math.nan}, "beta"),
        ({"num_actions": 2, "max_trajectory_len": 0}, "max_trajectory_len"),
    ],
)
def test_create_task_invalid_config(
    client: tamrm.Client, task_id: str, kwargs: dict[str, object], field: str
) -> None:
    with pytest.raises(tamrm.InvalidArgument) as err:
        client.create_task(task_id, **kwargs)  # type: ignore[arg-type]
    assert field in err.value.details
    with pytest.raises(tamrm.TaskNotFound):
        client.get_task(task_id)


@pytest.mark.parametrize("bad_id", ["", "has space", "bäd", "x" * 129, "semi;colon"])
def test_create_task_invalid_id(client: tamrm.Client, bad_id: str) -> None:
    with pytest.raises(tamrm.InvalidArgument) as err:
        client.create_task(bad_id, num_actions=2)
    assert "task_id" in err.value.details


def test_task_id_charset_accepted(client: tamrm.Client) -> None:
    tid = "Aa0._:/-" + "z" * 120
    assert len(tid) == 128
    try:
        assert client.create_task(tid, num_actions=2).task_id == tid
    finally:
        client.delete_task(tid)


def test_create_task_client_side_type_checks(client: tamrm.Client, task_id: str) -> None:
    with pytest.raises(ValueError, match="num_actions"):
        client.create_task(task_id, num_actions=-1)
    with pytest.raises(TypeError, match="pool_capacity"):
        client.create_task(task_id, num_actions=2, pool_capacity=2.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="alpha"):
        client.create_task(task_id, num_actions=2, alpha="big")  # type: ignore[arg-type]
    with pytest.raises(tamrm.TaskNotFound):
        client.get_task(task_id)


def test_unknown_task_is_not_found_everywhere(client: tamrm.Client, task_id: str) -> None:
    calls = [
        lambda: client.get_task(task_id),
        lambda: client.delete_task(task_id),
        lambda: client.reset_pool(task_id),
        lambda: client.get_pool(task_id),
        lambda: client.add_trajectory(task_id, [0], 1.0),
        lambda: client.session(task_id, 1),
    ]
    for call in calls:
        with pytest.raises(tamrm.TaskNotFound) as err:
            call()
        assert isinstance(err.value, tamrm.TamrmError)
        assert err.value.details


def test_list_tasks_sorted(client: tamrm.Client, task_id: str) -> None:
    ids = [f"{task_id}/b", f"{task_id}/a", f"{task_id}/c"]
    for tid in ids:
        client.create_task(tid, num_actions=2)
    listed = [t.task_id for t in client.list_tasks()]
    assert listed == sorted(listed)
    assert [t for t in listed if t.startswith(task_id)] == sorted(ids)
    for tid in ids:
        client.delete_task(tid)
    assert not [t for t in (x.task_id for x in client.list_tasks()) if t.startswith(task_id)]


def test_delete_task(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    client.delete_task(task_id)
    with pytest.raises(tamrm.TaskNotFound):
        client.get_task(task_id)
    with pytest.raises(tamrm.TaskNotFound):
        client.delete_task(task_id)
    # The id can be reused, with another config.
    assert client.create_task(task_id, num_actions=4).config.num_actions == 4


def test_add_trajectory_pool_rules(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=3, pool_capacity=3)
    v0 = client.get_task(task_id).stats.pool_version
    results = [
        client.add_trajectory(task_id, np.array([0, 1, 2], dtype=np.int64), 5.0),
        client.add_trajectory(task_id, np.array([2, 2], dtype=np.int32), 1.0),
        client.add_trajectory(task_id, [1, 1, 1, 1], 1.0),
    ]
    assert [r.inserted for r in results] == [True, True, True]
    assert [r.pool_version for r in results] == [v0 + 1, v0 + 2, v0 + 3]
    # Full: equal to the minimum is discarded, strictly greater replaces the lowest
    # score with the lowest seq.
    discarded = client.add_trajectory(task_id, [0], 1.0)
    assert not discarded.inserted and discarded.pool_version == v0 + 3
    replaced = client.add_trajectory(task_id, [2, 1], 2.0)
    assert replaced.inserted and replaced.pool_version == v0 + 4

    pool = client.get_pool(task_id)
    assert pool.task_id == task_id
    assert pool.pool_version == v0 + 4
    assert len(pool) == 3
    seqs = [t.seq for t in pool.trajectories]
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
    got = [(t.actions.tolist(), t.score) for t in pool.trajectories]
    assert got == [([0, 1, 2], 5.0), ([1, 1, 1, 1], 1.0), ([2, 1], 2.0)]
    for t in pool.trajectories:
        assert t.actions.dtype == np.int64 and t.actions.ndim == 1
    assert pool.scores.tolist() == [5.0, 1.0, 2.0]
    assert pool.lengths.tolist() == [3, 4, 2]

    stats = client.get_task(task_id).stats
    assert stats.pool_size == 3
    assert stats.min_length == 2
    assert stats.best_score == 5.0
    assert stats.worst_score == 1.0


def test_episodes_completed_counts_stream_episodes_only(client: tamrm.Client, task_id: str) -> None:
    # TaskStats.episodes_completed: "Episodes ended by Shape streams on this task, whether
    # their trajectory was stored or not" (proto); AddTrajectory is not an episode.
    client.create_task(task_id, num_actions=2, pool_capacity=1)
    client.add_trajectory(task_id, [0, 1], 2.0)
    assert not client.add_trajectory(task_id, [1], 1.0).inserted
    with client.session(task_id, 1) as s:
        s.step([0], [0.0], terminated=[True])  # score 0.0 < 2.0: discarded, still counted
    stats = client.get_task(task_id).stats
    assert stats.episodes_completed == 1
    assert stats.pool_size == 1


def test_add_trajectory_truncates_to_max_len(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, max_trajectory_len=4)
    client.add_trajectory(task_id, [1, 0, 1, 0, 1, 1, 1], 1.0)
    assert client.get_pool(task_id).trajectories[0].actions.tolist() == [1, 0, 1, 0]


def test_add_trajectory_continuous(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, action_dim=3, pool_capacity=2)
    acts = np.array([[0.5, -1.0, 2.0], [0.25, 0.0, 1e-3]], dtype=np.float64)
    assert client.add_trajectory(task_id, acts, -3.5).inserted
    (traj,) = client.get_pool(task_id).trajectories
    assert traj.actions.shape == (2, 3)
    assert traj.actions.dtype == np.float32
    np.testing.assert_array_equal(traj.actions, acts.astype(np.float32))
    assert traj.score == -3.5
    assert len(traj) == 2
    with pytest.raises(tamrm.InvalidArgument):  # m = 2 for a task with action_dim = 3
        client.add_trajectory(task_id, np.zeros((2, 2)), 1.0)
    with pytest.raises(tamrm.InvalidArgument):  # discrete actions for a continuous task
        client.add_trajectory(task_id, [0, 1], 1.0)
    with pytest.raises(tamrm.InvalidArgument):
        client.add_trajectory(task_id, np.array([[np.nan, 0.0, 0.0]]), 1.0)
    assert len(client.get_pool(task_id)) == 1


def test_add_trajectory_invalid(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=3)
    version = client.get_task(task_id).stats.pool_version
    with pytest.raises(tamrm.InvalidArgument) as err:
        client.add_trajectory(task_id, [0, 3], 1.0)
    assert "action" in err.value.details
    with pytest.raises(tamrm.InvalidArgument):
        client.add_trajectory(task_id, np.zeros(0, dtype=np.int64), 1.0)
    with pytest.raises(tamrm.InvalidArgument) as err:
        client.add_trajectory(task_id, [0, 1], math.inf)
    assert "score" in err.value.details
    with pytest.raises(tamrm.InvalidArgument):
        client.add_trajectory(task_id, np.zeros((2, 3)), 1.0)  # vectors for a discrete task
    # Client-side checks: nothing sent.
    with pytest.raises(TypeError):
        client.add_trajectory(task_id, np.array([0.5, 1.0]), 1.0)
    with pytest.raises(ValueError):
        client.add_trajectory(task_id, [-1, 0], 1.0)
    task = client.get_task(task_id)
    assert task.stats.pool_size == 0
    assert task.stats.pool_version == version


def test_reset_pool(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, pool_capacity=2)
    client.add_trajectory(task_id, [0, 1], 1.0)
    client.add_trajectory(task_id, [1, 1], 2.0)
    before = client.get_task(task_id).stats
    task = client.reset_pool(task_id)
    assert task.stats.pool_size == 0
    assert task.stats.pool_version == before.pool_version + 1
    pool = client.get_pool(task_id)
    assert len(pool) == 0 and pool.pool_version == before.pool_version + 1
    # seq keeps increasing after a reset.
    client.add_trajectory(task_id, [0], 0.0)
    (traj,) = client.get_pool(task_id).trajectories
    assert traj.seq > 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unavailable() -> None:
    with tamrm.Client(f"127.0.0.1:{_free_port()}", timeout=2.0) as dead:
        with pytest.raises(tamrm.Unavailable) as err:
            dead.list_tasks()
        assert err.value.code is not None and err.value.code.name == "UNAVAILABLE"
        with pytest.raises(tamrm.Unavailable):
            dead.session("x", 1)
        with pytest.raises(tamrm.Unavailable):
            dead.wait_ready(timeout=0.5)


def test_error_hierarchy() -> None:
    for cls in (
        tamrm.InvalidArgument,
        tamrm.TaskNotFound,
        tamrm.AlreadyExists,
        tamrm.ResourceExhausted,
        tamrm.FailedPrecondition,
        tamrm.Unavailable,
        tamrm.DeadlineExceeded,
        tamrm.SessionClosed,
    ):
        assert issubclass(cls, tamrm.TamrmError)
    assert str(tamrm.TaskNotFound("task 'x' not found")) == "NOT_FOUND: task 'x' not found"


def test_status_codes_map_to_exceptions() -> None:
    """Every status the server documents maps to its class, also from the native
    extension's (code number, message) form; the numbers are gRPC's wire values."""
    import grpc

    from tamrm import _native
    from tamrm._errors import from_native, from_status

    for code in grpc.StatusCode:  # the codes' numbers are gRPC's own
        assert tamrm.StatusCode(code.value[0]).name == code.name

    expected = {
        tamrm.StatusCode.INVALID_ARGUMENT: tamrm.InvalidArgument,
        tamrm.StatusCode.NOT_FOUND: tamrm.TaskNotFound,
        tamrm.StatusCode.ALREADY_EXISTS: tamrm.AlreadyExists,
        tamrm.StatusCode.RESOURCE_EXHAUSTED: tamrm.ResourceExhausted,
        tamrm.StatusCode.FAILED_PRECONDITION: tamrm.FailedPrecondition,
        tamrm.StatusCode.UNAVAILABLE: tamrm.Unavailable,
        tamrm.StatusCode.DEADLINE_EXCEEDED: tamrm.DeadlineExceeded,
    }
    for code, cls in expected.items():
        err = from_status(code, "open.num_envs: must be >= 1")
        assert type(err) is cls
        assert err.code == code and err.details == "open.num_envs: must be >= 1"
        native = from_native(_native.StatusError(code.value, "m"))
        assert type(native) is cls and native.code is code and native.details == "m"
    other = from_status(tamrm.StatusCode.INTERNAL, "boom")
    assert type(other) is tamrm.TamrmError and other.code == tamrm.StatusCode.INTERNAL
    assert from_native(_native.StatusError(99, "odd")).code is tamrm.StatusCode.UNKNOWN


def test_deadline_exceeded(server: tamrm.LocalServer) -> None:
    # A deadline already past when the call starts: the call fails on the client.
    with tamrm.Client(server.address, timeout=-1.0) as hurried:
        with pytest.raises(tamrm.DeadlineExceeded) as err:
            hurried.list_tasks()
    assert err.value.code is not None and err.value.code.name == "DEADLINE_EXCEEDED"
