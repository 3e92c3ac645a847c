"""Sending the agent steps :class:`KnnShaping` collected, and writing the answers back.

One ``Session.step`` per task (per agent step, when an agent has several new ones), then
per row the shaped reward into the episode's rewards and the shaping's parts into the
info of the step's next observation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from tamrm._session import Session
from tamrm.rllib._episodes import item, put

__all__ = ["ShapingCounts", "Row", "Slot", "send_rows"]


@dataclass
class Slot:
    """One (sub-environment, agent) of a task's session."""

    session: Session
    env_id: int
    task_id: str


@dataclass
class Row:
    """One agent step to send: where it goes and where its answer is written."""

    slot: Slot
    sa_episode: Any
    index: int
    action: Any
    reward: float
    terminated: bool
    truncated: bool
    score: float | None


@dataclass
class ShapingCounts:
    """What a :class:`KnnShaping` sent (see :meth:`KnnShaping.counts`).

    Attributes:
        agent_steps: Agent steps shaped (one row each).
        episodes: Agent episodes ended (a terminated or truncated last step).
        abandoned: Agent episodes abandoned (the sub-environment was reset, or the
            multi-agent episode ended, before the agent's episode ended; SPEC §12).
    """

    agent_steps: int = 0
    episodes: int = 0
    abandoned: int = 0

    def __add__(self, other: ShapingCounts) -> ShapingCounts:
        return ShapingCounts(
            self.agent_steps + other.agent_steps,
            self.episodes + other.episodes,
            self.abandoned + other.abandoned,
        )


def send_rows(
    rows: list[Row], env_action: Callable[[Any, Any], Any], counts: ShapingCounts
) -> tuple[float, int]:
    """Shape ``rows`` (not empty) and write the answers into their episodes.

    ``env_action(action, space)`` is the action the env received for a continuous task's
    module action. ``counts`` gets the agent steps and the agent episodes ended. Returns
    the sum of r(t) over the rows and how many had the kNN term active.
    """
    by_task: dict[str, list[Row]] = {}
    for row in rows:
        by_task.setdefault(row.slot.task_id, []).append(row)
    knn_sum = 0.0
    active = 0
    for task_rows in by_task.values():
        # One batch per task; an agent with several new steps (never, with RLlib's
        # EnvRunners: one call per env step) gets one batch per step, in order.
        while task_rows:
            batch: list[Row] = []
            rest: list[Row] = []
            seen: set[int] = set()
            for row in task_rows:
                (rest if row.slot.env_id in seen else batch).append(row)
                seen.add(row.slot.env_id)
            knn_sum, active = _step(batch, env_action, counts, knn_sum, active)
            task_rows = rest
    counts.agent_steps += len(rows)
    return knn_sum, active


def _step(
    rows: list[Row],
    env_action: Callable[[Any, Any], Any],
    counts: ShapingCounts,
    knn_sum: float,
    active: int,
) -> tuple[float, int]:
    """One ``Session.step`` of ``rows`` (one task's, at most one per slot)."""
    session = rows[0].slot.session
    config = session.config
    size = len(rows)
    if config.discrete:
        actions: npt.NDArray[Any] = np.fromiter(
            (int(r.action) for r in rows), dtype=np.int64, count=size
        )
    else:
        actions = np.stack(
            [
                np.asarray(
                    env_action(r.action, r.sa_episode.action_space), dtype=np.float64
                ).reshape(config.action_dim)
                for r in rows
            ]
        )
    scores = {i: r.score for i, r in enumerate(rows) if r.score is not None}
    result = session.step(
        actions,
        np.fromiter((r.reward for r in rows), dtype=np.float64, count=size),
        np.fromiter((r.terminated for r in rows), dtype=np.bool_, count=size),
        np.fromiter((r.truncated for r in rows), dtype=np.bool_, count=size),
        env_ids=np.fromiter((r.slot.env_id for r in rows), dtype=np.int64, count=size),
        episode_scores=scores or None,
    )
    columns = zip(
        rows,
        result.rewards.tolist(),
        result.knn_rewards.tolist(),
        result.potentials.tolist(),
        result.steps.tolist(),
        result.knn_active.tolist(),
        strict=True,
    )
    for row, shaped, knn, potential, step, knn_active in columns:
        sa = row.sa_episode
        put(sa.rewards, row.index, shaped)
        info = dict(item(sa.infos, row.index + 1) or {})
        info.update(
            original_reward=row.reward,
            knn_reward=knn,
            potential=potential,
            shaping_step=step,
            knn_active=knn_active,
            pool_version=result.pool_version,
        )
        # A new dict: RLlib repeats the previous info object for an agent that
        # terminates without an observation.
        put(sa.infos, row.index + 1, info)
        if row.terminated or row.truncated:
            counts.episodes += 1
    knn_sum += float(result.knn_rewards.sum())
    active += int(result.knn_active.sum())
    return knn_sum, active
