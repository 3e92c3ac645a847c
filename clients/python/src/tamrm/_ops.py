"""The unary RPCs without I/O: requests built, answers decoded, once for both clients.

Each operation is a generator that yields the :class:`Rpc` calls it needs and receives
their answers (``answer = yield Rpc(...)``); its return value is the client's result. The
clients (:class:`tamrm.Client`, :class:`tamrm.Engine`) only run the calls (:func:`run`
with their transport); everything else about a call is here.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Mapping
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy.typing as npt
from google.protobuf.message import Message

from tamrm._batch import prepare_trajectory
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._types import AddTrajectoryResult, Pool, Task, Trajectory, config_to_pb

__all__ = [
    "Op",
    "Rpc",
    "add_trajectory",
    "create_task",
    "delete_task",
    "get_pool",
    "get_task",
    "list_tasks",
    "reset_pool",
    "run",
]

_T = TypeVar("_T")


@dataclass(frozen=True)
class Rpc:
    """One unary call: the ``ShapingStub`` method's name and its request."""

    method: str
    request: Message


#: An operation: yields calls, receives their answers, returns the result.
Op = Generator[Rpc, Any, _T]


@dataclass(frozen=True)
class _Done(Generic[_T]):
    value: _T


def _advance(op: Op[_T], answer: Any) -> Rpc | _Done[_T]:
    """Give ``op`` the answer to its last call; return its next call, or its result."""
    try:
        return op.send(answer)
    except StopIteration as stop:
        return _Done(stop.value)


def run(op: Op[_T], call: Callable[[Rpc], Any]) -> _T:
    """Run ``op`` to its result, answering each of its calls with ``call(rpc)``."""
    step = _advance(op, None)
    while isinstance(step, Rpc):
        step = _advance(op, call(step))
    return step.value


def create_task(task_id: str, config: Mapping[str, Any]) -> Op[Task]:
    """``CreateTask``; ``config`` maps ``TaskConfig`` field names to values (None: default)."""
    request = pb.CreateTaskRequest(task_id=task_id, config=config_to_pb(config))
    return Task._from_pb((yield Rpc("CreateTask", request)))


def get_task(task_id: str) -> Op[Task]:
    """``GetTask``."""
    return Task._from_pb((yield Rpc("GetTask", pb.GetTaskRequest(task_id=task_id))))


def list_tasks() -> Op[list[Task]]:
    """``ListTasks``."""
    msg = yield Rpc("ListTasks", pb.ListTasksRequest())
    return [Task._from_pb(t) for t in msg.tasks]


def delete_task(task_id: str) -> Op[None]:
    """``DeleteTask``."""
    yield Rpc("DeleteTask", pb.DeleteTaskRequest(task_id=task_id))


def reset_pool(task_id: str) -> Op[Task]:
    """``ResetPool``."""
    return Task._from_pb((yield Rpc("ResetPool", pb.ResetPoolRequest(task_id=task_id))))


def get_pool(task_id: str) -> Op[Pool]:
    """``GetPool``, plus ``GetTask`` for the action dimension of a continuous pool."""
    msg = yield Rpc("GetPool", pb.GetPoolRequest(task_id=task_id))
    action_dim = 0
    if any(len(t.action_vectors) for t in msg.trajectories):
        action_dim = (yield from get_task(task_id)).config.action_dim
    return Pool(
        task_id=msg.task_id,
        pool_version=int(msg.pool_version),
        trajectories=[Trajectory._from_pb(t, action_dim) for t in msg.trajectories],
    )


def add_trajectory(task_id: str, actions: npt.ArrayLike, score: float) -> Op[AddTrajectoryResult]:
    """``AddTrajectory``."""
    request = pb.AddTrajectoryRequest(
        task_id=task_id, trajectory=prepare_trajectory(actions, score)
    )
    msg = yield Rpc("AddTrajectory", request)
    return AddTrajectoryResult(inserted=bool(msg.inserted), pool_version=int(msg.pool_version))
