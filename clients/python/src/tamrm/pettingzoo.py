"""PettingZoo wrappers: shape every agent's reward through tamrm (extra ``tamrm[pettingzoo]``).

One pool for every agent, or one per agent, role or team::

    engine = tamrm.Engine()
    engine.create_task("spread", num_actions=5)
    env = tamrm.pettingzoo.ShapedParallel(simple_spread_v3.parallel_env(), engine, "spread")

    # one task per role: ``task`` maps an agent to its task id
    env = tamrm.pettingzoo.ShapedParallel(env, engine, lambda agent: agent.split("_")[0])

The wrappers open one session per task, with one environment slot per agent of
``possible_agents`` mapped to it, and send each task's agents of a step in one batch.
An agent's episode starts at its first action and ends on its terminated or truncated
step (the pool update of SPEC §6); after that the agent is not shaped again until
``reset``, which abandons the episodes still unfinished (SPEC §12).

``ShapedParallel`` shapes the rewards ``step`` returns. ``ShapedAEC`` shapes what
``last()`` reports at an agent's turn: the reward accumulated since its previous turn,
as the outcome of the action it took then; an agent that terminated or truncated is
shaped at the turn on which it is removed (``step(None)``). Each shaped agent's
``infos[agent]`` gets the keys of :data:`tamrm.gym.INFO_KEYS`. docs/multi-agent.md tells
which pool layout to choose and how to train with SuperSuit and Stable-Baselines3.
"""

from __future__ import annotations

import itertools
import os
import weakref
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from pettingzoo.utils.env import AECEnv, ParallelEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper, BaseWrapper

from tamrm._client import Client
from tamrm._closing import Closing
from tamrm._engine import Engine
from tamrm._errors import TaskNotFound
from tamrm._session import Session
from tamrm._values import split_values
from tamrm._wrapping import check_action_space
from tamrm.gym import INFO_KEYS

__all__ = ["INFO_KEYS", "AgentValueFn", "ShapedAEC", "ShapedParallel", "TaskMap"]

#: ``values(agent, obs)``: V(s) of one agent's observation (a number), or its Q(s, ·)
#: row (``num_actions`` numbers), for the potential term F.
AgentValueFn: TypeAlias = Callable[[Any, Any], "float | npt.ArrayLike"]

#: A task id for every agent, or ``task(agent) -> task id``.
TaskMap: TypeAlias = "str | Callable[[Any], str]"

# Engines pickled by a wrapper in this process (SuperSuit copies an env by pickling it,
# even to use it in the same process): the copy finds its engine here by number.
_ENGINE_KEYS: weakref.WeakKeyDictionary[Engine, int] = weakref.WeakKeyDictionary()
_ENGINES: weakref.WeakValueDictionary[int, Engine] = weakref.WeakValueDictionary()
_NEXT_ENGINE_KEY = itertools.count(1)


def _pickled_api(api: Engine | Client) -> object:
    """What a pickled wrapper holds for ``api``: the client, or a same-process engine mark."""
    if not isinstance(api, Engine):
        return api
    key = _ENGINE_KEYS.get(api)
    if key is None:
        key = next(_NEXT_ENGINE_KEY)
        _ENGINE_KEYS[api] = key
        _ENGINES[key] = api
    return ("tamrm.Engine", os.getpid(), key)


def _unpickled_api(held: object) -> Engine | Client:
    if not isinstance(held, tuple):
        assert isinstance(held, (Engine, Client))
        return held
    _, pid, key = held
    engine = _ENGINES.get(key) if pid == os.getpid() else None
    if engine is None:
        raise TypeError(
            "a tamrm.Engine lives in one process: a wrapper on it can be copied (or pickled "
            "and unpickled) in that process only, while the engine exists; for worker "
            "processes (SuperSuit's num_cpus > 0, RLlib's env runners) run a server "
            "(tamrm serve) and pass a tamrm.Client"
        )
    return engine


@dataclass
class _Move:
    """One agent's step, as sent: its action, the reward and ends of its outcome."""

    agent: Any
    action: Any
    reward: float
    terminated: bool
    truncated: bool
    obs: Any = None
    next_obs: Any = None
    score: float | None = None


class _Pools:
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

    def shape(self, moves: Iterable[_Move]) -> dict[Any, tuple[float, dict[str, Any]]]:
        """Shape the moves: one ``step`` per task; per agent its reward and its info keys."""
        by_task: dict[str, list[_Move]] = {}
        for move in moves:
            self.known(move.agent)
            by_task.setdefault(self.task_of[move.agent], []).append(move)
        shaped: dict[Any, tuple[float, dict[str, Any]]] = {}
        for task_id, batch in by_task.items():
            shaped.update(self._shape_task(task_id, batch))
        return shaped

    def _shape_task(
        self, task_id: str, batch: list[_Move]
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

    def _values(self, batch: list[_Move]) -> dict[str, npt.NDArray[np.float64]]:
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
            "api": _pickled_api(self.api),
            "task": self.task,
            "values": self.values,
            "score_key": self.score_key,
            "local": self.local,
        }


def _pools_from_state(env: Any, state: Mapping[str, Any]) -> _Pools:
    return _Pools(
        env,
        _unpickled_api(state["api"]),
        state["task"],
        state["values"],
        state["score_key"],
        state["local"],
    )


class _Shaped(Closing):
    """What both wrappers share: their sessions, pickling and closing."""

    env: Any
    _pools: _Pools

    def __init__(
        self,
        env: ParallelEnv[Any, Any, Any] | AECEnv[Any, Any, Any],
        api: Engine | Client,
        task: TaskMap,
        *,
        values: AgentValueFn | None = None,
        score_key: str | None = None,
        local: bool = False,
    ) -> None:
        super().__init__(env)  # type: ignore[call-arg]  # the PettingZoo wrapper's
        self._pools = _Pools(env, api, task, values, score_key, local)
        self._forget()

    def _forget(self) -> None:
        """Drop the per-agent state of the env's episode (a reset, a new copy)."""
        raise NotImplementedError

    @property
    def sessions(self) -> dict[str, Session]:
        """The open sessions by task id (one environment slot per agent of the task)."""
        return self._pools.sessions

    def __getstate__(self) -> dict[str, Any]:
        return {"env": self.env, **self._pools.state()}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.env = state["env"]
        self._pools = _pools_from_state(self.env, state)
        self._forget()

    def close(self) -> None:
        """Close the env, then the sessions the wrapper opened."""
        try:
            self.env.close()
        finally:
            self._pools.close()


class ShapedParallel(_Shaped, BaseParallelWrapper[Any, Any, Any]):  # type: ignore[misc]
    """Shape the rewards of a PettingZoo ``ParallelEnv`` through tamrm.

    Every ``step`` sends the agents that acted, one batch per task: an agent's action,
    its reward, whether it terminated or truncated, and with ``values`` V or Q of its
    previous and new observation. It returns the shaped rewards; ``infos[agent]`` gets
    :data:`tamrm.gym.INFO_KEYS` (``original_reward`` is the env's reward). Agents that
    did not act (not in ``actions``, or appearing on this step) keep the env's reward.

    An agent's episode starts at its first action, also mid-way through the env's
    episode, and ends on its terminated or truncated step: that step updates its task's
    pool (SPEC §6), and the agent is not shaped again before ``reset``. ``reset``
    abandons the episodes still unfinished (SPEC §12: dropped, not stored).

    Put it on the env before SuperSuit's ``black_death_v3`` (whose padding hides an
    agent's end and would send the dead agent's padded steps).

    Args:
        env: The parallel env; every agent of ``possible_agents`` gets a slot, and its
            action space (``env.action_space(agent)``) must match its task's config.
        api: A :class:`tamrm.Engine` or a :class:`tamrm.Client`.
        task: A task id that every agent shares, or ``task(agent) -> task id`` (per agent,
            role or team). The tasks must exist.
        values: Optional ``values(agent, obs)`` returning V(s) (a number) or the Q(s, ·)
            row of ``obs``; without it F = 0.
        score_key: Optional ``infos[agent]`` key holding the agent's episode score S on
            its ending step; without it the score is the sum of its rewards (SPEC §6).
        local: Open local sessions (a :class:`tamrm.Client` only; SPEC §13).

    Raises:
        TaskNotFound: A task does not exist (the message names it and its agents).
        ValueError: An agent's action space does not match its task (the message names
            both), or the env has no ``possible_agents``.
        TypeError: ``api`` or ``task`` is of the wrong type.

    The wrapper pickles (SuperSuit's vector envs copy it by pickling, RLlib by
    cloudpickle): the copy opens its own sessions on the same tasks (on an engine: in
    the same process only) and must be reset before it steps. :meth:`close` (or leaving
    a ``with`` block) closes the env and the sessions the wrapper opened.
    """

    def _forget(self) -> None:
        # Per agent: its last observation (for V(s)), and whether its episode ended.
        self._obs: dict[Any, Any] = {}
        self._ended: set[Any] = set()

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[Any, Any], dict[Any, dict[str, Any]]]:
        """Reset the env; abandon the agents' unfinished episodes (SPEC §12)."""
        obs, infos = self.env.reset(seed=seed, options=options)
        self._pools.abandon_all()
        self._forget()
        self._obs.update(obs)
        return obs, infos

    def step(
        self, actions: dict[Any, Any]
    ) -> tuple[
        dict[Any, Any],
        dict[Any, float],
        dict[Any, bool],
        dict[Any, bool],
        dict[Any, dict[str, Any]],
    ]:
        """Step the env and return the shaped rewards (the env's are in ``infos``)."""
        live = set(self.env.agents)
        obs, rewards, terminations, truncations, infos = self.env.step(actions)
        pools = self._pools
        moves: list[_Move] = []
        for agent, action in actions.items():
            if agent not in live or agent in self._ended or agent not in rewards:
                continue
            terminated = bool(terminations.get(agent, False))
            truncated = bool(truncations.get(agent, False))
            move = _Move(agent, action, float(rewards[agent]), terminated, truncated)
            if pools.values is not None:
                move.obs, move.next_obs = self._observations(agent, obs, terminated)
            move.score = pools.score(infos.get(agent), terminated or truncated)
            moves.append(move)
            if terminated or truncated:
                self._ended.add(agent)
        self._obs.update(obs)
        if not moves:
            return obs, rewards, terminations, truncations, infos
        shaped = pools.shape(moves)
        rewards = dict(rewards)
        infos = dict(infos)
        for agent, (reward, info) in shaped.items():
            rewards[agent] = reward
            infos[agent] = {**infos.get(agent, {}), **info}
        return obs, rewards, terminations, truncations, infos

    def _observations(
        self, agent: Any, obs: Mapping[Any, Any], terminated: bool
    ) -> tuple[Any, Any]:
        """The agent's observation before and after this step (for its values)."""
        if agent not in self._obs:
            raise RuntimeError(f"no observation of agent {agent!r}: call reset() before step()")
        before = self._obs[agent]
        if agent in obs:
            return before, obs[agent]
        if terminated:
            return before, before  # V(s') of a terminal state is 0 whatever is sent
        raise ValueError(
            f"the env returned no observation of agent {agent!r} after it acted and did not "
            "terminate: its V(s') is needed for the potential term"
        )


class ShapedAEC(_Shaped, BaseWrapper[Any, Any, Any]):  # type: ignore[misc]
    """Shape the rewards of a PettingZoo ``AECEnv`` through tamrm, per agent turn.

    At an agent's turn, ``last()`` reports the reward it accumulated since its previous
    turn: the outcome of the action it took then. The wrapper shapes that reward when the
    turn comes (after the ``step`` or ``reset`` that selects the agent), with that action,
    the agent's ``terminations`` / ``truncations`` and with ``values`` V or Q of its
    observation at the previous turn and now, so ``last()`` reports the shaped reward
    and ``infos[agent]`` the keys of :data:`tamrm.gym.INFO_KEYS` (``original_reward``:
    what the env's ``last()`` reports). An agent's first turn has nothing to shape. An
    agent that terminated or truncated is shaped at the turn on which it is removed
    (``step(None)``): its last action's outcome ends its episode (SPEC §6); it is not
    shaped again before ``reset``, which abandons the unfinished episodes (SPEC §12).

    ``rewards`` holds the env's per-step rewards, except that the reward of the step
    that selected a shaped agent carries the shaping, so that the rewards since an
    agent's turn add up to what ``last()`` reports (PettingZoo's invariant, also what
    ``aec_to_parallel`` sums).

    Args:
        env: The AEC env; every agent of ``possible_agents`` gets a slot, and its action
            space must match its task's config.
        api: A :class:`tamrm.Engine` or a :class:`tamrm.Client`.
        task: A task id that every agent shares, or ``task(agent) -> task id``. The
            tasks must exist.
        values: Optional ``values(agent, obs)`` returning V(s) or the Q(s, ·) row of
            ``obs`` (as ``observe(agent)`` returns it); without it F = 0.
        score_key: Optional ``infos[agent]`` key holding the agent's episode score S at
            its removal turn; without it the score is the sum of its rewards.
        local: Open local sessions (a :class:`tamrm.Client` only; SPEC §13).

    Raises:
        TaskNotFound, ValueError, TypeError: As :class:`ShapedParallel`.

    Pickling and :meth:`close` are as for :class:`ShapedParallel`.
    """

    rewards: dict[Any, float]
    _cumulative_rewards: dict[Any, float]

    def _forget(self) -> None:
        # Per agent: the action (and observation) of its last turn, not shaped yet.
        self._pending: dict[Any, tuple[Any, Any]] = {}
        # Per agent whose turn it is and whose outcome was shaped: the info keys.
        self._shaping: dict[Any, dict[str, Any]] = {}
        self._ended: set[Any] = set()

    @property
    def infos(self) -> dict[Any, dict[str, Any]]:
        """The env's infos; a shaped agent's (at its turn) with the shaping keys added."""
        infos: dict[Any, dict[str, Any]] = self.env.infos
        if not self._shaping:
            return infos
        return {
            agent: {**info, **self._shaping[agent]} if agent in self._shaping else info
            for agent, info in infos.items()
        }

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        """Reset the env; abandon the agents' unfinished episodes (SPEC §12)."""
        self.env.reset(seed=seed, options=options)
        self._pools.abandon_all()
        self._forget()
        self.rewards = {agent: float(r) for agent, r in self.env.rewards.items()}
        self._cumulative_rewards = {
            agent: float(r) for agent, r in self.env._cumulative_rewards.items()
        }

    def step(self, action: Any) -> None:
        """Step the selected agent; shape the outcome of the next agent's previous turn."""
        env = self.env
        agent = env.agent_selection
        acts = not (env.terminations[agent] or env.truncations[agent]) and action is not None
        obs = env.observe(agent) if acts and self._pools.values is not None else None
        env.step(action)
        if acts and agent not in self._ended:
            self._pools.known(agent)
            self._pending[agent] = (action, obs)
        self._cumulative_rewards[agent] = 0.0
        self._shaping.pop(agent, None)
        self._after_step()

    def _after_step(self) -> None:
        env = self.env
        rewards = {agent: float(r) for agent, r in env.rewards.items()}
        gone = [agent for agent in self._pending if agent not in rewards]
        if gone:  # removed by the env without an end: nothing to store
            self._pools.abandon(gone)
            for agent in gone:
                del self._pending[agent]
        # An agent's rewards between its turns are reported whole, shaped, on the step
        # that selects it again (0 before): they add up to what last() reports exactly.
        for agent in self._pending:
            rewards[agent] = 0.0
        selected = env.agent_selection if env.agents else None
        if selected in self._pending:
            action, obs = self._pending.pop(selected)
            terminated = bool(env.terminations[selected])
            truncated = bool(env.truncations[selected])
            ends = terminated or truncated
            move = _Move(
                selected,
                action,
                float(env._cumulative_rewards[selected]),
                terminated,
                truncated,
                obs,
                env.observe(selected) if self._pools.values is not None else None,
                self._pools.score(env.infos.get(selected), ends),
            )
            rewards[selected], self._shaping[selected] = self._pools.shape([move])[selected]
            if ends:
                self._ended.add(selected)
        self.rewards = rewards
        self._cumulative_rewards = {
            agent: self._cumulative_rewards.get(agent, 0.0) + r for agent, r in rewards.items()
        }
