"""Checks of a session step's arguments, and the conversion of a trajectory to a message.

:class:`tamrm.Session` calls the ``checked_*`` helpers for any argument that is not
already a numpy array of the canonical dtype and shape: a wrong shape or dtype raises a
``ValueError``/``TypeError`` naming the argument, before anything is sent. A continuous
action that is not finite, or too large for the 32-bit float it is sent as, raises
:class:`tamrm.InvalidArgument` naming the row and the value as the caller gave it; the
other per-entry checks (finiteness of rewards, values and scores) are made by the native
extension with the same messages. Either way nothing is sent and the session stays usable
(SPEC §8). :func:`prepare_trajectory` builds the ``Trajectory`` of ``add_trajectory``;
:func:`abandon_ids` checks the argument of :meth:`tamrm.Session.abandon`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from tamrm._errors import InvalidArgument
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._types import TaskConfig

__all__ = [
    "abandon_ids",
    "checked_actions",
    "checked_env_ids",
    "checked_flags",
    "checked_real",
    "checked_scores",
    "prepare_trajectory",
]

_UINT32_MAX = 2**32 - 1


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
