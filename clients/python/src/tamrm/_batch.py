"""Validation of a session step's arrays and their conversion to a columnar ``StepBatch``.

Everything here runs before a request is sent: a wrong shape or dtype raises a
``ValueError``/``TypeError`` naming the argument and nothing reaches the server. A
non-finite number (a NaN from a diverging critic), or one too large for the 32-bit float
it is sent as (values, Q-values, action vectors), raises :class:`tamrm.InvalidArgument`
naming the argument, the row and the value as the caller gave it; nothing is sent, so the
session stays usable (SPEC §8: the server would reject the batch anyway, but its status
ends the stream). The server's other value checks (scores on entries that do not end an
episode when given as a mapping) are left to it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from tamrm._errors import InvalidArgument
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._types import TaskConfig

__all__ = [
    "PreparedBatch",
    "StepInput",
    "abandon_ids",
    "checked_actions",
    "checked_env_ids",
    "checked_flags",
    "checked_real",
    "checked_scores",
    "prepare_batch",
    "prepare_trajectory",
]

_UINT32_MAX = 2**32 - 1


@dataclass(frozen=True)
class StepInput:
    """The arguments of one :meth:`tamrm.Session.step`, as the caller gave them."""

    actions: npt.ArrayLike
    rewards: npt.ArrayLike
    terminated: npt.ArrayLike | None = None
    truncated: npt.ArrayLike | None = None
    values: npt.ArrayLike | None = None
    next_values: npt.ArrayLike | None = None
    q_values: npt.ArrayLike | None = None
    next_q_values: npt.ArrayLike | None = None
    episode_scores: npt.ArrayLike | Mapping[int, float] | None = None
    env_ids: npt.ArrayLike | None = None


@dataclass(frozen=True)
class PreparedBatch:
    """A validated step: the request to send and what the session needs to track."""

    request: pb.ShapeRequest
    env_ids: npt.NDArray[np.int64]
    done: npt.NDArray[np.bool_]
    #: The rows' actions (``(B,)`` integers or ``(B, action_dim)`` floats as sent) and
    #: environment rewards, kept by the session to resume its episodes (SPEC §9).
    actions: npt.NDArray[Any]
    rewards: npt.NDArray[np.float64]

    @property
    def size(self) -> int:
        """Number of entries B."""
        return int(self.env_ids.shape[0])


def _array(name: str, value: object) -> npt.NDArray[Any]:
    if value is None:
        raise TypeError(f"{name} must be an array, got None")
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} could not be converted to an array: {exc}") from exc
    return arr


def _check_shape(name: str, arr: npt.NDArray[Any], shape: tuple[int, ...]) -> None:
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def checked_real(name: str, value: object, shape: tuple[int, ...]) -> npt.NDArray[np.float64]:
    arr = _array(name, value)
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must hold real numbers (int or float), got dtype {arr.dtype}")
    _check_shape(name, arr, shape)
    return arr.astype(np.float64, copy=False)


def _finite(name: str, arr: npt.NDArray[Any], float32: bool, rows: list[int] | None = None) -> None:
    """Raise :class:`InvalidArgument` for the first entry that is not finite (as sent).

    ``float32``: the field is sent as a 32-bit float, so a finite entry beyond its range
    (e.g. ``1e39``) is reported as given rather than as the ``inf`` it would become.
    ``rows``: the row of each entry of a 1-D ``arr``, if not its position.
    """
    wrong = ~np.isfinite(arr)
    if float32:
        wrong |= np.abs(arr) > _FLOAT32_MAX
    bad = np.argwhere(wrong)
    if bad.size == 0:
        return
    index = tuple(int(i) for i in bad[0])
    value = float(arr[index])
    if rows is not None:
        index = (rows[index[0]],)
    where = f"{name}[{', '.join(map(str, index))}]"
    if np.isfinite(value):
        why = f"does not fit the 32-bit float it is sent as (|x| <= {_FLOAT32_MAX:.4g})"
    else:
        why = "is not finite"
    raise InvalidArgument(
        f"{where} = {value!r} {why}; nothing was sent, the session is still usable"
    )


def checked_flags(name: str, value: object, size: int) -> npt.NDArray[np.bool_]:
    if value is None:
        return np.zeros(size, dtype=np.bool_)
    arr = _array(name, value)
    if arr.dtype.kind == "b":
        pass
    elif arr.dtype.kind in "iu":
        if arr.size and not np.isin(arr, (0, 1)).all():
            raise ValueError(f"{name} must hold booleans (or 0/1 integers)")
    else:
        raise TypeError(f"{name} must hold booleans, got dtype {arr.dtype}")
    _check_shape(name, arr, (size,))
    return arr.astype(np.bool_, copy=False)


def checked_actions(config: TaskConfig, value: object, size: int) -> npt.NDArray[Any]:
    """Check the actions against the task: ``int64`` ``(B,)`` or ``float32`` ``(B, action_dim)``."""
    arr = _array("actions", value)
    shape: tuple[int, ...]
    if config.discrete:
        kinds, what, shape = "iu", "integer actions for a discrete task", (size,)
    else:
        kinds, what = "iuf", "real action vectors for a continuous task"
        shape = (size, config.action_dim)
    if arr.dtype.kind not in kinds:
        raise TypeError(f"actions must hold {what}, got dtype {arr.dtype}")
    _check_shape("actions", arr, shape)
    if not config.discrete:
        _finite("actions", arr.astype(np.float64, copy=False), float32=True)
        return arr.astype(np.float32, copy=False)
    if arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < 0 or hi >= config.num_actions:
            bad = lo if lo < 0 else hi
            raise ValueError(f"actions must be in 0..{config.num_actions - 1}, got {bad}")
    return arr.astype(np.int64, copy=False)


def _add_actions(
    batch: pb.StepBatch, config: TaskConfig, value: object, size: int
) -> npt.NDArray[Any]:
    """Check the actions, write them to ``actions``/``action_vectors``; return them as sent."""
    arr = checked_actions(config, value, size)
    if config.discrete:
        batch.actions.extend(arr.tolist())
    else:
        batch.action_vectors.extend(arr.ravel().tolist())
    return arr


def checked_env_ids(value: object, num_envs: int) -> npt.NDArray[np.int64] | None:
    """The ``env_ids`` argument as ``int64``, or ``None`` for "row i is env i"."""
    if value is None:
        return None
    arr = _array("env_ids", value)
    if arr.dtype.kind not in "iu":
        raise TypeError(f"env_ids must hold integers, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"env_ids must be one-dimensional, got shape {arr.shape}")
    ids = arr.astype(np.int64, copy=False)
    if ids.size and (int(ids.min()) < 0 or int(ids.max()) >= num_envs):
        raise ValueError(f"env_ids must be in 0..{num_envs - 1}")
    return ids


def _add_values(batch: pb.StepBatch, config: TaskConfig, step: StepInput, size: int) -> None:
    """Check the (optional) state values or Q-values and write them to the batch."""
    if (step.values is None) != (step.next_values is None):
        raise TypeError("values and next_values must be given together")
    if (step.q_values is None) != (step.next_q_values is None):
        raise TypeError("q_values and next_q_values must be given together")
    if step.values is not None and step.q_values is not None:
        raise TypeError("give either values/next_values or q_values/next_q_values, not both")
    columns: list[tuple[str, object, Any, tuple[int, ...]]] = []
    if step.values is not None:
        columns += [
            ("values", step.values, batch.values, (size,)),
            ("next_values", step.next_values, batch.next_values, (size,)),
        ]
    if step.q_values is not None:
        if not config.discrete:
            raise ValueError("q_values are only accepted by discrete tasks (num_actions > 0)")
        shape: tuple[int, ...] = (size, config.num_actions)
        columns += [
            ("q_values", step.q_values, batch.q_values, shape),
            ("next_q_values", step.next_q_values, batch.next_q_values, shape),
        ]
    for name, value, field, shape in columns:
        arr = checked_real(name, value, shape)
        _finite(name, arr, float32=True)
        field.extend(arr.ravel().tolist())


def checked_scores(
    value: npt.ArrayLike | Mapping[int, float], done: npt.NDArray[np.bool_]
) -> dict[int, float]:
    """``{row: score}`` from the ``episode_scores`` argument (an array or a mapping)."""
    size = int(done.shape[0])
    if not isinstance(value, Mapping):
        sc = checked_real("episode_scores", value, (size,))
        rows = np.flatnonzero(done & ~np.isnan(sc))
        return dict(zip(rows.tolist(), sc[rows].tolist(), strict=True))
    scores: dict[int, float] = {}
    for key, score in value.items():
        if isinstance(key, bool) or not isinstance(key, (int, np.integer)):
            raise TypeError("episode_scores keys must be row indices (int)")
        if not 0 <= int(key) < size:
            raise ValueError(f"episode_scores key {key} is not a row index < {size}")
        scores[int(key)] = float(score)
    return scores


def prepare_batch(config: TaskConfig, num_envs: int, step: StepInput) -> PreparedBatch:
    """Validate one step's arrays and build its ``ShapeRequest``.

    See :meth:`tamrm.Session.step` for the meaning of the arguments.

    Raises:
        TypeError: An argument has the wrong dtype, or only one of a pair was given.
        ValueError: An argument has the wrong shape or an out-of-range entry.
        InvalidArgument: A number is not finite or does not fit its 32-bit field.
    """
    given_ids = checked_env_ids(step.env_ids, num_envs)
    ids = np.arange(num_envs, dtype=np.int64) if given_ids is None else given_ids
    size = int(ids.shape[0])

    rew = checked_real("rewards", step.rewards, (size,))
    _finite("rewards", rew, float32=False)
    term = checked_flags("terminated", step.terminated, size)
    trunc = checked_flags("truncated", step.truncated, size)
    done = term | trunc

    batch = pb.StepBatch(
        env_ids=[] if given_ids is None else given_ids.tolist(), rewards=rew.tolist()
    )
    if step.terminated is not None and term.any():
        batch.terminated.extend(term.tolist())
    if step.truncated is not None and trunc.any():
        batch.truncated.extend(trunc.tolist())
    actions = _add_actions(batch, config, step.actions, size)
    _add_values(batch, config, step, size)
    if step.episode_scores is not None:
        scores = checked_scores(step.episode_scores, done)
        _finite("episode_scores", np.array(list(scores.values())), False, list(scores))
        for key, score in scores.items():
            batch.episode_scores[key] = score

    return PreparedBatch(
        request=pb.ShapeRequest(steps=batch),
        env_ids=ids,
        done=done,
        actions=actions,
        rewards=rew,
    )


def prepare_trajectory(actions: npt.ArrayLike, score: float) -> pb.Trajectory:
    """Build a ``Trajectory`` message from an action array and a score.

    A one-dimensional integer array is a discrete trajectory (``actions``); a
    two-dimensional real array ``(L, action_dim)`` is a continuous one (``action_vectors``).
    """
    arr = _array("actions", actions)
    if isinstance(score, bool) or not isinstance(score, (int, float, np.number)):
        raise TypeError(f"score must be a float, got {type(score).__name__}")
    if arr.ndim == 1 and arr.dtype.kind in "iu":
        if arr.size and (int(arr.min()) < 0 or int(arr.max()) > _UINT32_MAX):
            raise ValueError("actions must be non-negative integers")
        return pb.Trajectory(actions=arr.astype(np.int64).tolist(), score=float(score))
    if arr.ndim == 2 and arr.dtype.kind in "iuf":
        return pb.Trajectory(
            action_vectors=arr.astype(np.float32).ravel().tolist(), score=float(score)
        )
    raise TypeError(
        "actions must be a 1-D integer array (discrete task) or a 2-D real array "
        f"(L, action_dim) (continuous task), got dtype {arr.dtype} shape {arr.shape}"
    )


def abandon_ids(value: npt.ArrayLike, num_envs: int) -> list[int]:
    """The ``abandon`` argument checked: integers, each in ``0..num_envs-1``, none twice."""
    arr = np.atleast_1d(np.asarray(value))
    if arr.size == 0:
        return []
    if arr.dtype.kind not in "iu":
        raise TypeError(f"abandon: env ids must be integers, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"abandon: env ids must be one-dimensional, got shape {arr.shape}")
    ids: list[int] = arr.astype(np.int64).tolist()
    seen: set[int] = set()
    for env in ids:
        if not 0 <= env < num_envs:
            raise ValueError(
                f"abandon: env id {env} is not in 0..{num_envs - 1} (num_envs={num_envs})"
            )
        if env in seen:
            raise ValueError(f"abandon: env {env} is listed twice")
        seen.add(env)
    return ids
