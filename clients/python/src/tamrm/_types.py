"""Plain-Python views of the server's messages (no protobuf objects in the public API)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypedDict, TypeVar

import numpy as np
import numpy.typing as npt
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from tamrm._proto.tamrm.v1 import shaping_pb2 as pb

__all__ = [
    "CONFIG_FIELDS",
    "AddTrajectoryResult",
    "Pool",
    "StepResult",
    "Task",
    "TaskConfig",
    "TaskOptions",
    "TaskStats",
    "Trajectory",
]

_D = TypeVar("_D")


class TaskOptions(TypedDict, total=False):
    """The keyword arguments of ``create_task``: the proto's ``TaskConfig`` fields.

    Every key is optional; ``None`` or a missing key means "the server's default"
    (SPEC §1.1). See :class:`TaskConfig` for their meaning.
    """

    num_actions: int | None
    action_dim: int | None
    pool_capacity: int | None
    k: int | None
    start_step: int | None
    min_pool_size: int | None
    alpha: float | None
    beta: float | None
    gamma: float | None
    max_trajectory_len: int | None
    gate_potential: bool | None
    require_score_spread: bool | None


#: The ``TaskConfig`` fields, in proto order; ``Client.create_task`` takes them as keywords.
CONFIG_FIELDS: tuple[str, ...] = tuple(TaskOptions.__annotations__)
_UINT32_MAX = 2**32 - 1

# The Python type of each proto scalar type used by TaskConfig and TaskStats.
_PY_TYPES: dict[int, type] = {
    FieldDescriptor.TYPE_UINT32: int,
    FieldDescriptor.TYPE_UINT64: int,
    FieldDescriptor.TYPE_DOUBLE: float,
    FieldDescriptor.TYPE_BOOL: bool,
}


def _scalars(cls: type[_D], msg: Message) -> _D:
    """Build the dataclass ``cls`` from the same-named scalar fields of ``msg``."""
    by_name = msg.DESCRIPTOR.fields_by_name
    return cls(
        **{
            f.name: _PY_TYPES[by_name[f.name].type](getattr(msg, f.name))
            for f in dataclasses.fields(cls)  # type: ignore[arg-type]
        }
    )


@dataclass(frozen=True)
class TaskConfig:
    """A task's resolved configuration (SPEC §1.1); every default filled in by the server.

    Attributes:
        num_actions: Discrete action space size n (0 for a continuous task).
        action_dim: Continuous action dimension m (0 for a discrete task).
        pool_capacity: Most trajectories the memory pool keeps, |D|.
        k: Neighbours used by the kNN reward.
        start_step: First step index t at which the kNN reward may be non-zero.
        min_pool_size: The kNN reward is active only with at least this many trajectories.
        alpha: Weight of the kNN reward r(t).
        beta: Weight of the potential term F.
        gamma: Discount in F = gamma * V(s') - V(s).
        max_trajectory_len: Most actions recorded per episode.
        gate_potential: Whether the potential term F counts only on steps where the kNN
            term is active (SPEC v1.1 §4; ``False`` from servers that predate it).
        require_score_spread: Whether the kNN term is active only while the pool's scores
            differ, S_max > S_min (SPEC v1.3 §3): a pool of equal scores then pays no flat
            bonus per step (``False`` from servers that predate it).
    """

    num_actions: int
    action_dim: int
    pool_capacity: int
    k: int
    start_step: int
    min_pool_size: int
    alpha: float
    beta: float
    gamma: float
    max_trajectory_len: int
    gate_potential: bool = False
    require_score_spread: bool = False

    @property
    def discrete(self) -> bool:
        """Whether the task has a discrete action space (``num_actions > 0``)."""
        return self.num_actions > 0

    @classmethod
    def _from_pb(cls, msg: pb.TaskConfig) -> TaskConfig:
        return _scalars(cls, msg)


@dataclass(frozen=True)
class TaskStats:
    """Live statistics of a task (the proto's ``TaskStats``).

    Attributes:
        pool_size: Trajectories in the pool now.
        pool_version: Incremented by every insert, replace and reset; never decreases.
        min_length: Length of the shortest stored trajectory (0 if the pool is empty).
        best_score: Highest stored episode score (0 if empty).
        worst_score: Lowest stored episode score (0 if empty).
        episodes_completed: Episodes ended on the task, stored or not.
        steps_shaped: Step entries shaped on the task by all streams.
        open_streams: Shape streams open on the task now.
    """

    pool_size: int
    pool_version: int
    min_length: int
    best_score: float
    worst_score: float
    episodes_completed: int
    steps_shaped: int
    open_streams: int

    @classmethod
    def _from_pb(cls, msg: pb.TaskStats) -> TaskStats:
        return _scalars(cls, msg)


@dataclass(frozen=True)
class Task:
    """A task: its id, its resolved configuration and its statistics at the time of the call."""

    task_id: str
    config: TaskConfig
    stats: TaskStats

    @classmethod
    def _from_pb(cls, msg: pb.Task) -> Task:
        return cls(
            task_id=msg.task_id,
            config=TaskConfig._from_pb(msg.config),
            stats=TaskStats._from_pb(msg.stats),
        )


@dataclass(frozen=True)
class Trajectory:
    """One stored episode.

    Attributes:
        actions: For a discrete task an ``int64`` array of shape ``(L,)``; for a continuous
            task a ``float32`` array of shape ``(L, action_dim)``.
        score: The episode score S.
        seq: The server-assigned insertion number (strictly increasing per task).
    """

    actions: npt.NDArray[np.int64] | npt.NDArray[np.float32]
    score: float
    seq: int

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @classmethod
    def _from_pb(cls, msg: pb.Trajectory, action_dim: int) -> Trajectory:
        if len(msg.action_vectors) > 0:
            dim = action_dim if action_dim > 0 else len(msg.action_vectors)
            vectors = np.array(msg.action_vectors, dtype=np.float32).reshape(-1, dim)
            return cls(actions=vectors, score=float(msg.score), seq=int(msg.seq))
        actions = np.array(msg.actions, dtype=np.int64)
        return cls(actions=actions, score=float(msg.score), seq=int(msg.seq))


@dataclass(frozen=True)
class Pool:
    """A task's memory pool.

    Attributes:
        task_id: The task.
        pool_version: The pool's version at the time of the call.
        trajectories: Every stored trajectory, ordered by ``seq``.
    """

    task_id: str
    pool_version: int
    trajectories: list[Trajectory] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.trajectories)

    @property
    def scores(self) -> npt.NDArray[np.float64]:
        """The trajectories' scores as a ``float64`` array, in ``seq`` order."""
        return np.array([t.score for t in self.trajectories], dtype=np.float64)

    @property
    def lengths(self) -> npt.NDArray[np.int64]:
        """The trajectories' lengths as an ``int64`` array, in ``seq`` order."""
        return np.array([len(t) for t in self.trajectories], dtype=np.int64)


@dataclass(frozen=True)
class AddTrajectoryResult:
    """The answer to :meth:`tamrm.Client.add_trajectory`.

    Attributes:
        inserted: Whether the trajectory was stored (inserted or replaced another one).
        pool_version: The pool version after the call.
    """

    inserted: bool
    pool_version: int


@dataclass(frozen=True)
class StepResult:
    """The shaped rewards of one :meth:`tamrm.Session.step`, one row per entry sent.

    ``rewards == original_rewards + alpha * knn_rewards + beta * potentials``.

    Attributes:
        rewards: ``float64`` (B,): the shaped rewards R_meta.
        knn_rewards: ``float64`` (B,): the kNN reward r(t) (0 where not active).
        potentials: ``float64`` (B,): the potential term F (0 where no values were sent).
        steps: ``int64`` (B,): each entry's step index t within its episode.
        knn_active: ``bool`` (B,): whether the kNN term was active for the entry.
        pool_version: The task's pool version after the batch.
        env_ids: ``int64`` (B,): the environment of each row.
    """

    rewards: npt.NDArray[np.float64]
    knn_rewards: npt.NDArray[np.float64]
    potentials: npt.NDArray[np.float64]
    steps: npt.NDArray[np.int64]
    knn_active: npt.NDArray[np.bool_]
    pool_version: int
    env_ids: npt.NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    @classmethod
    def _from_pb(cls, msg: pb.ShapedBatch, env_ids: npt.NDArray[np.int64]) -> StepResult:
        return cls(
            rewards=np.array(msg.rewards, dtype=np.float64),
            knn_rewards=np.array(msg.knn_rewards, dtype=np.float64),
            potentials=np.array(msg.potentials, dtype=np.float64),
            steps=np.array(msg.steps, dtype=np.int64),
            knn_active=np.array(msg.knn_active, dtype=np.bool_),
            pool_version=int(msg.pool_version),
            env_ids=env_ids,
        )

    @classmethod
    def _empty(cls, pool_version: int) -> StepResult:
        return cls(
            rewards=np.zeros(0, dtype=np.float64),
            knn_rewards=np.zeros(0, dtype=np.float64),
            potentials=np.zeros(0, dtype=np.float64),
            steps=np.zeros(0, dtype=np.int64),
            knn_active=np.zeros(0, dtype=np.bool_),
            pool_version=pool_version,
            env_ids=np.zeros(0, dtype=np.int64),
        )


def config_to_pb(values: Mapping[str, Any]) -> pb.TaskConfig:
    """Build a ``TaskConfig`` message from keyword arguments; ``None`` means "server default".

    Raises:
        TypeError: A value has the wrong type (e.g. a float for an integer field).
        ValueError: An integer does not fit the field's unsigned 32-bit range.
    """
    unknown = set(values) - set(CONFIG_FIELDS)
    if unknown:
        raise TypeError(f"unknown TaskConfig field(s): {', '.join(sorted(unknown))}")
    msg = pb.TaskConfig()
    for name in CONFIG_FIELDS:
        value = values.get(name)
        if value is None:
            continue
        kind = _PY_TYPES[msg.DESCRIPTOR.fields_by_name[name].type]
        if kind is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError(f"{name} must be a bool, got {type(value).__name__}")
            setattr(msg, name, bool(value))
        elif kind is int:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"{name} must be an int, got {type(value).__name__}")
            ivalue = int(value)
            if not 0 <= ivalue <= _UINT32_MAX:
                raise ValueError(f"{name} must be in 0..{_UINT32_MAX}, got {ivalue}")
            setattr(msg, name, ivalue)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise TypeError(f"{name} must be a float, got {type(value).__name__}")
            # Range and finiteness are the server's to check (INVALID_ARGUMENT).
            setattr(msg, name, float(value))
    return msg
