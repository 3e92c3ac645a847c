"""The sessions of a PettingZoo wrapper (:class:`Pools`): one per task, a slot per agent.

:class:`Pools` maps each agent of ``possible_agents`` to its task and its slot, opens the
sessions, checks the agents' action spaces, and shapes a step's agent moves
(:class:`Move`) in one ``Session.step`` per task.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from pettingzoo.utils.env import AECEnv, ParallelEnv

from tamrm._client import Client
from tamrm._engine import Engine
from tamrm._errors import TaskNotFound
from tamrm._session import Session
from tamrm._values import split_values
from tamrm._wrapping import check_action_space
from tamrm.gym import INFO_KEYS
from tamrm.pettingzoo._engines import pickled_api, unpickled_api

__all__ = ["AgentValueFn", "Move", "Pools", "TaskMap", "pools_from_state"]

#: ``values(agent, obs)``: V(s) of one agent's observation (a number), or its Q(s, ·)
#: row (``num_actions`` numbers), for the potential term F.
AgentValueFn: TypeAlias = Callable[[Any, Any], "float | npt.ArrayLike"]

#: A task id for every agent, or ``task(agent) -> task id``.
TaskMap: TypeAlias = "str | Callable[[Any], str]"


@dataclass
class Move:
    """One agent's step, as sent: its action, the reward and ends of its outcome."""

    agent: Any
    action: Any
    reward: float
    terminated: bool
    truncated: bool
    obs: Any = None
    next_obs: Any = None
    score: float | None = None


class Pools:
    """The sessions of a wrapper: one per task, one environment slot per agent mapped to it."""

    def __init__(
        self,
        env: ParallelEnv[Any, Any, Any] | AECEnv[Any, Any, Any],
        api: Engine | Client,
        task: TaskMap,
        values: AgentValueFn | None,
        score_key: str | None,
        local: bool,
    ) -> None:
        if not isinstance(api, (Engine, Client)):
            raise TypeError(f"api must be a tamrm.Engine or tamrm.Client, got {type(api).__name__}")
        if not isinstance(task, str) and not callable(task):
            raise TypeError(
                f"task must be a task id (str) or a callable agent -> task id, got "
                f"{type(task).__name__}"
            )
        try:
            agents = list(env.possible_agents)
        except AttributeError:
            raise ValueError(
                f"{env} has no possible_agents: the wrapper opens one environment slot per "
                "possible agent"
            ) from None
        if not agents:
            raise ValueError(f"{env} has no possible_agents")
        self.api = api
        self.task = task
        self.values = values
        self.score_key = score_key
        self.local = local
        self.task_of: dict[Any, str] = {}
        for agent in agents:
            task_id = task if isinstance(task, str) else task(agent)
            if not isinstance(task_id, str):
                raise TypeError(
                    f"task({agent!r}) returned {type(task_id).__name__} {task_id!r}; "
                    "expected a task id (str)"
                )
            self.task_of[agent] = task_id
        #: Per task, its agents in the order of ``possible_agents`` (agent i: slot i).
        self.agents_of: dict[str, list[Any]] = {}
        for agent, task_id in self.task_of.items():
            self.agents_of.setdefault(task_id, []).append(agent)
        self.slot_of = {
            agent: slot for members in self.agents_of.values() for slot, agent in enumerate(members)
        }
        self.sessions: dict[str, Session] = {}
        try:
            for task_id, members in self.agents_of.items():
                self.sessions[task_id] = self._open(task_id, members)
                for agent in members:
                    self._check_space(agent, env.action_space(agent))
        except BaseException:
            self.close()
            raise

    def _open(self, task_id: str, members: list[Any]) -> Session:
        try:
            return self.api.session(task_id, len(members), local=self.local)
        except TaskNotFound as exc:
            raise TaskNotFound(
                f"task {task_id!r} (of agents {', '.join(map(repr, members))}) does not exist: "
                "create it first (create_task) with the agents' action space",
                code=exc.code,
            ) from None

    def _check_space(self, agent: Any, space: spaces.Space[Any]) -> None:
        task_id = self.task_of[agent]
        try:
            check_action_space(space, self.sessions[task_id].config)
        except ValueError as exc:
            raise ValueError(f"agent {agent!r}, task {task_id!r}: {exc}") from None

    def known(self, agent: Any) -> bool:
        """Whether ``agent`` has a slot (else: an error naming it)."""
        if agent not in self.task_of:
            raise ValueError(
                f"agent {agent!r} is not in the env's possible_agents, which the wrapper "
                "maps to tasks when it is made"
            )
        return True

    def shape(self, moves: Iterable[Move]) -> dict[Any, tuple[float, dict[str, Any]]]:
        """Shape the moves: one ``step`` per task; per agent its reward and its info keys."""
        by_task: dict[str, list[Move]] = {}
        for move in moves:
            self.known(move.agent)
            by_task.setdefault(self.task_of[move.agent], []).append(move)
        shaped: dict[Any, tuple[float, dict[str, Any]]] = {}
        for task_id, batch in by_task.items():
            shaped.update(self._shape_task(task_id, batch))
        return shaped

    def _shape_task(
        self, task_id: str, batch: list[Move]
    ) -> Iterable[tuple[Any, tuple[float, dict[str, Any]]]]:
        session = self.sessions[task_id]
        slots = [self.slot_of[move.agent] for move in batch]
        env_ids = None
        if slots != list(range(session.num_envs)):
            env_ids = np.array(slots, dtype=np.int64)
        config = session.config
        if config.discrete:
            actions = np.array([int(move.action) for move in batch], dtype=np.int64)
        else:
            actions = np.stack(
                [np.asarray(move.action, dtype=np.float64).reshape(-1) for move in batch]
            )
        rewards = np.array([move.reward for move in batch], dtype=np.float64)
        scores = {row: move.score for row, move in enumerate(batch) if move.score is not None}
        result = session.step(
            actions,
            rewards,
            np.array([move.terminated for move in batch], dtype=np.bool_),
            np.array([move.truncated for move in batch], dtype=np.bool_),
            env_ids=env_ids,
            episode_scores=scores or None,
            **self._values(batch),
        )
        for row, move in enumerate(batch):
            info = dict(
                zip(
                    INFO_KEYS,
                    (
                        move.reward,
                        float(result.knn_rewards[row]),
                        float(result.potentials[row]),
                        int(result.steps[row]),
                        bool(result.knn_active[row]),
                        result.pool_version,
                    ),
                    strict=True,
                )
            )
            yield move.agent, (float(result.rewards[row]), info)

    def _values(self, batch: list[Move]) -> dict[str, npt.NDArray[np.float64]]:
        """The step keywords of V or Q of each move's observation and next observation."""
        if self.values is None:
            return {}
        rows: list[npt.NDArray[np.float64]] = []
        for which in ("obs", "next_obs"):
            for move in batch:
                value = np.asarray(self.values(move.agent, getattr(move, which)), np.float64)
                if value.ndim > 1:
                    raise ValueError(
                        f"values({move.agent!r}, obs) returned shape {value.shape}; expected "
                        "a number V(s) or a row Q(s, ·) of num_actions numbers"
                    )
                rows.append(value)
        shapes = {row.shape for row in rows}
        if len(shapes) > 1:
            raise ValueError(
                f"values(agent, obs) returned rows of different shapes {sorted(shapes)} for the "
                f"agents of task {self.task_of[batch[0].agent]!r}; return V(s) for every one "
                "or Q(s, ·) for every one"
            )
        return split_values(np.stack(rows), len(batch))

    def score(self, info: Mapping[str, Any] | None, ends: bool) -> float | None:
        """The episode score in ``info`` of an ending step (``score_key``), if any."""
        if self.score_key is None or not ends or info is None or self.score_key not in info:
            return None
        return float(info[self.score_key])

    def abandon(self, agents: Iterable[Any]) -> None:
        """Drop the unfinished episodes of ``agents`` (SPEC §12)."""
        by_task: dict[str, list[int]] = {}
        for agent in agents:
            by_task.setdefault(self.task_of[agent], []).append(self.slot_of[agent])
        for task_id, slots in by_task.items():
            session = self.sessions[task_id]
            going = [slot for slot in slots if session.episodes_in_progress[slot]]
            if going:
                session.abandon(going)

    def abandon_all(self) -> None:
        """Drop every unfinished episode (a reset)."""
        for session in self.sessions.values():
            going = np.flatnonzero(session.episodes_in_progress)
            if going.size:
                session.abandon(going)

    def close(self) -> None:
        """Close the sessions (what the wrapper opened; not ``api``)."""
        for session in self.sessions.values():
            session.close()

    def state(self) -> dict[str, Any]:
        """What a pickled wrapper keeps: how to open the sessions again."""
        return {
            "api": pickled_api(self.api),
            "task": self.task,
            "values": self.values,
            "score_key": self.score_key,
            "local": self.local,
        }


def pools_from_state(env: Any, state: Mapping[str, Any]) -> Pools:
    return Pools(
        env,
        unpickled_api(state["api"]),
        state["task"],
        state["values"],
        state["score_key"],
        state["local"],
    )
