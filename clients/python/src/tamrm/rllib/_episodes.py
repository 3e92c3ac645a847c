"""Reading and writing the buffers of RLlib's episodes (``InfiniteLookbackBuffer``).

Both connector pieces write rewards back into the episodes they are handed: the EnvRunner
side in place of the recorded reward (:func:`put`), the learner side into a copy
(:func:`add_rewards`, never into arrays a replay buffer may share).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["add_rewards", "item", "put"]


def item(buf: Any, k: int) -> Any:
    """Item ``k`` (0: the first after the lookback) of an episode's InfiniteLookbackBuffer."""
    data = buf.data
    if isinstance(data, list):  # an episode being sampled: index its list directly
        return data[buf.lookback + k]
    return buf.get(k)


def put(buf: Any, k: int, value: Any) -> None:
    """Overwrite item ``k`` of an episode's InfiniteLookbackBuffer."""
    if isinstance(buf.data, list):
        buf.data[buf.lookback + k] = value
    else:
        buf.set(new_data=value, at_indices=k)


def add_rewards(sa: Any, shaped: npt.NDArray[np.float64]) -> None:
    """Add ``shaped`` to the first ``len(shaped)`` rewards of ``sa``, in a new array."""
    buf = sa.rewards
    start = buf.lookback
    stop = start + shaped.shape[0]
    if isinstance(buf.data, np.ndarray):
        array = buf.data.astype(np.result_type(buf.data.dtype, np.float32), copy=True)
        array[start:stop] += shaped.astype(array.dtype)
        buf.data = array
    else:
        data = list(buf.data)
        for k in range(start, stop):
            data[k] = float(data[k]) + float(shaped[k - start])
        buf.data = data
