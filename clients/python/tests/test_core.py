"""The sans-I/O core shared by the sync and asyncio clients, driven without a server."""

from __future__ import annotations

import asyncio

import pytest

import tamrm
import tamrm.aio
from tamrm import _ops as ops
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb


def _answer(rpc: ops.Rpc) -> object:
    """A canned server: a continuous pool of one trajectory, its task with action_dim 2."""
    if rpc.method == "GetPool":
        traj = pb.Trajectory(action_vectors=[0.0, 1.0, 2.0, 3.0], score=1.5, seq=4)
        return pb.Pool(task_id=rpc.request.task_id, pool_version=7, trajectories=[traj])
    if rpc.method == "GetTask":
        return pb.Task(task_id=rpc.request.task_id, config=pb.TaskConfig(action_dim=2))
    raise AssertionError(rpc.method)


def test_get_pool_op_asks_for_the_action_dim() -> None:
    calls: list[str] = []

    def call(rpc: ops.Rpc) -> object:
        calls.append(rpc.method)
        return _answer(rpc)

    pool = ops.run(ops.get_pool("x"), call)
    assert calls == ["GetPool", "GetTask"]
    assert pool.pool_version == 7
    assert pool.trajectories[0].actions.tolist() == [[0.0, 1.0], [2.0, 3.0]]


def test_create_task_op_builds_the_request() -> None:
    op = ops.create_task(
        "t",
        {"num_actions": 3, "gate_potential": True, "require_score_spread": False, "k": None},
    )
    rpc = next(op)
    assert rpc.method == "CreateTask"
    assert rpc.request.task_id == "t"
    assert rpc.request.config.num_actions == 3
    assert rpc.request.config.gate_potential is True
    # An explicit False is sent (set, not left to the default).
    assert rpc.request.config.HasField("require_score_spread")
    assert rpc.request.config.require_score_spread is False
    assert not rpc.request.config.HasField("k")


def test_async_step_checks_its_arguments_when_awaited(
    server: tamrm.LocalServer, task_id: str
) -> None:
    """As before the refactor: a bad step raises at ``await``, not when it is called."""

    async def main() -> None:
        async with tamrm.aio.Client(server.address) as c:
            await c.create_task(task_id, num_actions=2)
            async with c.session(task_id, 1) as s:
                pending = s.step([5], [0.0])  # out of range: not raised yet
                with pytest.raises(ValueError, match="actions"):
                    await pending
                assert (await s.step([1], [0.0])).steps.tolist() == [0]

    asyncio.run(main())
