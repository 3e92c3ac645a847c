"""Helpers shared by the wrappers: value functions and observation batches."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

__all__ = [
    "ObsBatch",
    "ValueFn",
    "concat_obs",
    "select_obs",
    "set_obs_row",
    "split_values",
    "value_kwargs",
]

#: A batch of observations: an array with a leading batch axis, or a dict of batches.
ObsBatch: TypeAlias = "npt.NDArray[Any] | Mapping[str, ObsBatch]"

#: ``value_fn(observations) -> values``: given a batch of observations, returns V(s)
#: with shape ``(B,)`` (or ``(B, 1)``), or Q(s, ·) with shape ``(B, num_actions)``.
ValueFn = Callable[[ObsBatch], npt.ArrayLike]


def concat_obs(first: ObsBatch, second: ObsBatch) -> ObsBatch:
    """Concatenate two observation batches along the batch axis (arrays or dicts of arrays)."""
    if isinstance(first, Mapping):
        return {key: concat_obs(first[key], second[key]) for key in first}
    return np.concatenate([np.asarray(first), np.asarray(second)], axis=0)


def select_obs(obs: ObsBatch, rows: npt.NDArray[np.intp] | None) -> ObsBatch:
    """Select rows of an observation batch (``rows=None``: all rows, no copy)."""
    if rows is None:
        return obs
    if isinstance(obs, Mapping):
        return {key: select_obs(value, rows) for key, value in obs.items()}
    return np.asarray(obs)[rows]


def copy_obs(obs: ObsBatch) -> ObsBatch:
    """Copy an observation batch (arrays or dicts of arrays)."""
    if isinstance(obs, Mapping):
        return {key: copy_obs(value) for key, value in obs.items()}
    return np.array(obs, copy=True)


def set_obs_row(obs: ObsBatch, row: int, value: Any) -> None:
    """Overwrite row ``row`` of an observation batch in place."""
    if isinstance(obs, Mapping):
        for key in obs:
            set_obs_row(obs[key], row, value[key])
        return
    obs[row] = value


def value_kwargs(
    value_fn: ValueFn | None, obs: ObsBatch, next_obs: ObsBatch, size: int
) -> dict[str, npt.NDArray[np.float64]]:
    """Evaluate ``value_fn`` once on ``obs`` and ``next_obs`` and return step keywords.

    Returns ``{}`` without a value function, ``{"values", "next_values"}`` for state
    values, ``{"q_values", "next_q_values"}`` for Q-values.

    Raises:
        ValueError: ``value_fn`` returned an array of an unexpected shape.
    """
    if value_fn is None or size == 0:
        return {}
    return split_values(value_fn(concat_obs(obs, next_obs)), size)


def split_values(values: npt.ArrayLike, size: int) -> dict[str, npt.NDArray[np.float64]]:
    """Split the values of ``size`` observations followed by their ``size`` successors.

    ``values`` holds V(s) ``(2 * size,)`` (or ``(2 * size, 1)``) or Q(s, ·)
    ``(2 * size, num_actions)``; the result is the step keywords of :func:`value_kwargs`.

    Raises:
        ValueError: ``values`` has an unexpected shape.
    """
    out = np.asarray(values, dtype=np.float64)
    if out.ndim == 2 and out.shape == (2 * size, 1):
        out = out[:, 0]
    if out.shape == (2 * size,):
        return {"values": out[:size], "next_values": out[size:]}
    if out.ndim == 2 and out.shape[0] == 2 * size:
        return {"q_values": out[:size], "next_q_values": out[size:]}
    raise ValueError(
        f"value_fn returned shape {out.shape} for {2 * size} observations; expected "
        f"({2 * size},) state values or ({2 * size}, num_actions) Q-values"
    )
