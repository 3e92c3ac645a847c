"""Ray RLlib (new API stack): the kNN term on the EnvRunners, the potential term on the learners.

Two ConnectorV2 pieces split ``R_meta = R + alpha * r(t) + beta * F`` where the data is:

- :class:`KnnShaping`, an env-to-module piece, runs on every EnvRunner (single- or
  multi-agent). After each vector step it sends every agent step the EnvRunner just
  recorded (action, reward, terminated, truncated) to tamrm, one ``Session.step`` per task,
  and writes ``R + alpha * r(t)`` back into the episode, in place of the reward RLlib
  recorded. Each EnvRunner process has one :class:`tamrm.Client` and, per task, one session
  with a slot per (sub-environment, agent); by default a local session (SPEC §13), so a
  step never waits on the network and only episode ends reach the server.
- :class:`PotentialShaping`, a learner piece, adds ``beta * (gamma * V(s') - V(s))`` with
  the learner's own value function (``V(s') = 0`` after a terminated step, V of the real
  last observation after a truncated one), once per episode chunk: a chunk it has shaped
  is marked and never shaped again, and it writes to a copy of the rewards, never into
  arrays a replay buffer may share.

Wiring both::

    import tamrm, tamrm.rllib
    from ray.rllib.algorithms.ppo import PPOConfig

    task = tamrm.Client("shaping:50051").create_task("cartpole", num_actions=2)
    config = (
        PPOConfig()
        .environment("CartPole-v1")
        .env_runners(env_to_module_connector=tamrm.rllib.knn_connector("cartpole",
                                                                       address="shaping:50051"))
        .learners(learner_connector=tamrm.rllib.potential_connector(task))
    )

Multi-agent: ``task`` is a task id shared by every agent, or a function ``agent_id -> task
id`` (like ``policy_mapping_fn``: a pool per agent, role or team). Each agent's own
SingleAgentEpisode inside the MultiAgentEpisode is one tamrm episode: an agent that dies
ends its episode then (the pool update of SPEC §6), one that appears later starts its
episode at its first step, and the reward shaped is exactly the agent step's reward RLlib
trains on (rewards an agent receives between two of its observations included).
"""

from __future__ import annotations

import functools
import threading
import weakref
from collections.abc import Callable, Collection, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import tree
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core import DEFAULT_AGENT_ID, DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModule
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.rllib.utils.spaces.space_utils import batch as batch_structs
from ray.rllib.utils.spaces.space_utils import clip_action, unsquash_action

from tamrm._address import parse_targets
from tamrm._client import Client
from tamrm._connection import ConnectionOptions, resolve_api_key
from tamrm._errors import TamrmError
from tamrm._session import Session
from tamrm._types import Task, TaskConfig
from tamrm._wrapping import check_action_space
from tamrm.gym import INFO_KEYS

__all__ = [
    "INFO_KEYS",
    "KnnShaping",
    "PotentialShaping",
    "ShapingCounts",
    "TaskMap",
    "close_sessions",
    "knn_connector",
    "potential_connector",
    "process_client",
]

#: Which task an agent's episodes are shaped on: one task id for every agent, or a
#: function ``agent_id -> task id`` (per agent, role or team, like ``policy_mapping_fn``).
TaskMap = str | Callable[[Any], str]

#: The key under which :class:`PotentialShaping` marks an episode chunk it has shaped, in
#: the chunk's ``custom_data``: the (first, last + 1) agent timesteps it added F to.
POTENTIAL_MARK = "tamrm.potential_shaped"

_CLIENTS: dict[str, Client] = {}
_CLIENTS_LOCK = threading.Lock()


def process_client(
    address: str | Sequence[str] | None = None,
    api_key: str | None = None,
    **connection: Any,
) -> Client:
    """This process's :class:`tamrm.Client` for ``address`` (one per address and settings).

    Every :class:`KnnShaping` of a process (an EnvRunner, its evaluation twin in the same
    process, several pipelines) shares this one client and its connection.

    Args:
        address: The server, as :class:`tamrm.Client` takes it; ``None``: the
            ``TAMRM_ADDRESS`` environment variable of this process, else the default.
        api_key: The API key; ``None``: ``TAMRM_API_KEY`` of this process, else none.
        **connection: Further keywords of :class:`tamrm.Client` (``tls``,
            ``root_certificates``, ``timeout``, ...).
    """
    targets = parse_targets(address)
    key = resolve_api_key(api_key)
    ident = repr((targets, key, sorted(connection.items())))
    with _CLIENTS_LOCK:
        client = _CLIENTS.get(ident)
        if client is None:
            client = _CLIENTS[ident] = Client(list(targets), api_key=key, **connection)
        return client


def _task_of(task: TaskMap, agent_id: Any) -> str:
    """The task id of ``agent_id`` (checked)."""
    if isinstance(task, str):
        return task
    task_id = task(agent_id)
    if not isinstance(task_id, str):
        raise TypeError(
            f"the task function returned {task_id!r} for agent {agent_id!r}; "
            "it must return a task id (str)"
        )
    return task_id


def _check_task_map(task: object) -> None:
    if isinstance(task, str):
        if not task:
            raise ValueError("task must be a non-empty task id")
    elif not callable(task):
        raise TypeError(
            f"task must be a task id (str) or a function agent_id -> task id, "
            f"got {type(task).__name__}"
        )


@dataclass
class _Slot:
    """One (sub-environment, agent) of a task's session."""

    session: Session
    env_id: int
    task_id: str


@dataclass
class _EnvState:
    """What :class:`KnnShaping` knows about one sub-environment's current episode."""

    episode_id: str | None = None
    #: Per agent: the agent timestep up to which its steps are shaped (global ``t``).
    shaped: dict[Any, int] = field(default_factory=dict)
    #: Sum of the environment rewards of every agent in the episode so far (metrics).
    env_return: float = 0.0
    done: bool = False


@dataclass
class _Row:
    """One agent step to send: where it goes and where its answer is written."""

    slot: _Slot
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


def _close_all(sessions: dict[str, Session]) -> None:
    for session in sessions.values():
        session.close()


class KnnShaping(ConnectorV2):  # type: ignore[misc]
    """Env-to-module ConnectorV2 piece: shapes the EnvRunner's agent steps with tamrm.

    Add it first in ``config.env_runners(env_to_module_connector=...)`` (see
    :func:`knn_connector`); it changes no batch and no observation, only the rewards
    (and ``infos``) recorded in the episodes. Every agent step gets ``R + alpha * r(t)``
    (no values are sent: the potential term is :class:`PotentialShaping`'s, on the
    learner), and the info dict of the step's next observation gets the keys of
    :data:`INFO_KEYS` (``original_reward``, ``knn_reward``, ``knn_active``, ...).

    Nothing connects until the first episode arrives, so the pipelines RLlib builds
    without sampling (the driver's local EnvRunner) open nothing. Then the piece takes
    :func:`process_client` (or ``client``) and opens, per task, one session of
    ``num_envs * agents of the task`` slots. The tasks must exist, with action spaces
    matching each agent's (``Discrete(num_actions)``, or a ``Box`` of ``action_dim``
    elements).

    Episode boundaries: a step that terminates or truncates an agent ends its tamrm
    episode; an episode RLlib drops before it ended (a reset, a failed env step, a new
    ``sample(num_episodes=...)`` call) is abandoned (SPEC §12), and so is the episode of
    an agent that had no step left when its multi-agent episode ended.

    Args:
        input_observation_space: As for every ConnectorV2 (unused).
        input_action_space: As for every ConnectorV2 (unused).
        task: A task id, or a function ``agent_id -> task id``. In a single-agent env
            the function is called with RLlib's ``DEFAULT_AGENT_ID``.
        address: The server; ``None``: ``TAMRM_ADDRESS`` in the EnvRunner's process.
        api_key: The API key; ``None``: ``TAMRM_API_KEY`` in the EnvRunner's process.
        client: A client to use instead of :func:`process_client` (a
            :class:`tamrm.Client`, or a :class:`tamrm.Engine` for EnvRunners in this
            process only: an engine does not pickle).
        local: Local sessions (SPEC §13, the default): shaped in the EnvRunner against
            a followed copy of the pool, one message per episode end. ``False``: remote
            sessions, one round trip per task per vector step. Ignored with an engine.
        score_key: Optional key of the agent's ``info`` holding the episode score S on
            its last step (SPEC §6); without it the score is the sum of the agent's
            rewards.
        normalize_actions: Continuous tasks: whether the EnvRunners map the module's
            actions from [-1, 1] to the action space before the env sees them, RLlib's
            ``config.env_runners(normalize_actions=...)`` (default ``True``). The actions
            sent to tamrm are those the env received.
        clip_actions: Continuous tasks: RLlib's ``clip_actions`` (default ``False``).
        num_envs: The EnvRunner's number of sub-environments; ``None``: taken from the
            first call (always one episode per sub-environment).
        connection: Further keywords of :class:`tamrm.Client` (``tls``, ...).
    """

    def __init__(
        self,
        input_observation_space: Any = None,
        input_action_space: Any = None,
        *,
        task: TaskMap,
        address: str | Sequence[str] | None = None,
        api_key: str | None = None,
        client: Any = None,
        local: bool = True,
        score_key: str | None = None,
        normalize_actions: bool = True,
        clip_actions: bool = False,
        num_envs: int | None = None,
        connection: ConnectionOptions | None = None,
    ) -> None:
        super().__init__(input_observation_space, input_action_space)
        _check_task_map(task)
        if not isinstance(local, bool):
            raise TypeError(f"local must be a bool, got {type(local).__name__}")
        if score_key is not None and not isinstance(score_key, str):
            raise TypeError(f"score_key must be a str or None, got {type(score_key).__name__}")
        if num_envs is not None and (isinstance(num_envs, bool) or num_envs < 1):
            raise ValueError(f"num_envs must be a positive int or None, got {num_envs!r}")
        if client is not None and not hasattr(client, "session"):
            raise TypeError(
                f"client must be a tamrm.Client or tamrm.Engine, got {type(client).__name__}"
            )
        self.task = task
        self.address = address
        self.api_key = api_key
        self.client = client
        self.local = local
        self.score_key = score_key
        self.normalize_actions = normalize_actions
        self.clip_actions = clip_actions
        self.num_envs = num_envs
        self.connection: dict[str, Any] = dict(connection or {})
        self._reset_runtime()

    # -- runtime state (not pickled) -----------------------------------------------------

    def _reset_runtime(self) -> None:
        self._api: Any = None
        self._sessions: dict[str, Session] = {}
        self._slots: dict[tuple[int, Any], _Slot] = {}
        self._envs: list[_EnvState] = []
        self._index_of: dict[str, int] = {}
        self._agents: dict[str, list[Any]] = {}
        self._spaces: dict[Any, Any] = {}
        self._counts = ShapingCounts()
        self._pending_returns: list[float] = []
        self._finalizer: weakref.finalize[Any, Any] | None = None

    def __getstate__(self) -> dict[str, Any]:
        # Pickled (RLlib's cloudpickle, checkpoints) as its configuration: a copy opens
        # its own sessions, on its own process's client.
        state = {k: v for k, v in self.__dict__.items() if not k.startswith("_") or k in _KEEP}
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._reset_runtime()

    # -- public ----------------------------------------------------------------------

    @property
    def sessions(self) -> Mapping[str, Session]:
        """The open sessions, by task id (empty before the first episode)."""
        return dict(self._sessions)

    def counts(self) -> ShapingCounts:
        """Agent steps shaped, agent episodes ended and abandoned so far by this piece."""
        return ShapingCounts(
            self._counts.agent_steps, self._counts.episodes, self._counts.abandoned
        )

    def close(self) -> ShapingCounts:
        """Close the sessions (a local one first reports its last steps); returns counts.

        Episodes in progress are discarded (SPEC §6). The piece opens new sessions if it
        is called again.
        """
        _close_all(self._sessions)
        if self._finalizer is not None:
            self._finalizer.detach()
        counts = self.counts()
        self._reset_runtime()
        return counts

    # -- the pipeline call ---------------------------------------------------------------

    def __call__(self, *, episodes: list[Any], batch: Any, metrics: Any = None, **_: Any) -> Any:
        """Shape the agent steps added to ``episodes`` since the last call; ``batch`` as is."""
        if episodes:
            self._shape(episodes, metrics)
        return batch

    def _shape(self, episodes: list[Any], metrics: Any) -> None:
        if self.num_envs is None:
            self.num_envs = len(episodes)
        if not self._envs:
            self._envs = [_EnvState() for _ in range(self.num_envs)]
        # The EnvRunners pass their ongoing episodes, one per sub-environment in order;
        # a multi-agent EnvRunner also passes the episodes that just ended, which this
        # piece has seen before, by themselves.
        positional = len(episodes) == self.num_envs
        placed: list[tuple[int, Any]] = []
        for position, episode in enumerate(episodes):
            index = self._index_of.get(episode.id_)
            if index is None:
                if not positional:
                    raise RuntimeError(
                        f"KnnShaping: episode {episode.id_!r} was never seen as one of the "
                        f"{self.num_envs} ongoing episodes of this EnvRunner (is num_envs "
                        "right?)"
                    )
                index = position
                self._start_episode(index, episode.id_)
            placed.append((index, episode))
        rows: list[_Row] = []
        for index, episode in placed:
            rows.extend(self._new_steps(index, episode))
        self._send(rows, metrics)
        for index, episode in placed:
            if episode.is_done and not self._envs[index].done:
                self._end_episode(index)
        if metrics is not None:
            for ret in self._pending_returns:
                metrics.log_value(("tamrm", "env_episode_return_mean"), ret, window=100)
            self._pending_returns.clear()

    def _start_episode(self, index: int, episode_id: str) -> None:
        """Track a new episode on sub-environment ``index``, abandoning an unfinished one."""
        state = self._envs[index]
        if state.episode_id is not None:
            del self._index_of[state.episode_id]
            if not state.done:
                self._abandon(index)
        self._envs[index] = _EnvState(episode_id=episode_id)
        self._index_of[episode_id] = index

    def _end_episode(self, index: int) -> None:
        """The multi-agent (or single-agent) episode ended: no agent's episode goes on."""
        state = self._envs[index]
        self._abandon(index)
        state.done = True
        self._pending_returns.append(state.env_return)

    def _abandon(self, index: int) -> None:
        """Abandon the tamrm episodes in progress on the slots of sub-environment ``index``."""
        for (env_index, _agent), slot in self._slots.items():
            if env_index != index or slot.session.closed:
                continue
            if slot.session.episodes_in_progress[slot.env_id]:
                slot.session.abandon([slot.env_id])
                self._counts.abandoned += 1

    def _agent_episodes(self, episode: Any) -> Iterable[tuple[Any, Any]]:
        if isinstance(episode, MultiAgentEpisode):
            return list(episode.agent_episodes.items())
        return ((DEFAULT_AGENT_ID, episode),)

    def _new_steps(self, index: int, episode: Any) -> list[_Row]:
        """The agent steps of ``episode`` not yet shaped, as rows to send."""
        state = self._envs[index]
        rows: list[_Row] = []
        for agent_id, sa in self._agent_episodes(episode):
            start = state.shaped.get(agent_id, sa.t_started)
            first = max(start - sa.t_started, 0)
            length = len(sa)
            if first >= length:
                continue
            slot = self._slot(index, agent_id, episode, sa)
            for k in range(first, length):
                last = k == length - 1 and sa.is_done
                reward = float(_item(sa.rewards, k))
                state.env_return += reward
                score = None
                if last and self.score_key is not None:
                    info = _item(sa.infos, k + 1)
                    if self.score_key in info:
                        score = float(info[self.score_key])
                rows.append(
                    _Row(
                        slot,
                        sa,
                        k,
                        _item(sa.actions, k),
                        reward,
                        bool(last and sa.is_terminated),
                        bool(last and sa.is_truncated and not sa.is_terminated),
                        score,
                    )
                )
            state.shaped[agent_id] = sa.t_started + length
        return rows

    # -- sessions and slots ------------------------------------------------------------

    def _client(self) -> Any:
        if self._api is None:
            if self.client is not None:
                self._api = self.client
            else:
                self._api = process_client(self.address, self.api_key, **self.connection)
        return self._api

    def _slot(self, index: int, agent_id: Any, episode: Any, sa: Any) -> _Slot:
        slot = self._slots.get((index, agent_id))
        if slot is not None:
            return slot
        spaces = self._agent_spaces(episode)
        if agent_id not in spaces:
            raise ValueError(
                f"agent {agent_id!r} is not one of the env's possible agents "
                f"{list(spaces)}: KnnShaping gives each possible agent a session slot"
            )
        task_id = _task_of(self.task, agent_id)
        session = self._session(task_id, spaces)
        agents = self._agents[task_id]
        slot = _Slot(session, index * len(agents) + agents.index(agent_id), task_id)
        self._slots[(index, agent_id)] = slot
        return slot

    def _agent_spaces(self, episode: Any) -> dict[Any, Any]:
        """Every possible agent's action space (the env's order)."""
        if not self._spaces:
            if isinstance(episode, MultiAgentEpisode):
                spaces = episode.action_space
                if not spaces:
                    raise ValueError(
                        "KnnShaping needs the env's possible_agents (and their action "
                        "spaces): the multi-agent env declares none"
                    )
                self._spaces = dict(spaces.items())
            else:
                self._spaces = {DEFAULT_AGENT_ID: episode.action_space}
        return self._spaces

    def _session(self, task_id: str, spaces: dict[Any, Any]) -> Session:
        session = self._sessions.get(task_id)
        if session is not None:
            return session
        agents = [a for a in spaces if _task_of(self.task, a) == task_id]
        api = self._client()
        local = self.local and isinstance(api, Client)
        assert self.num_envs is not None
        try:
            session = Session(api, task_id, self.num_envs * len(agents), local=local)
        except TamrmError as exc:
            raise type(exc)(
                f"task {task_id!r} (agents {agents}): {exc.details}; create the task first "
                "(client.create_task) with the agents' action space",
                exc.code,
            ) from exc
        for agent in agents:
            try:
                check_action_space(spaces[agent], session.config)
            except ValueError as exc:
                session.close()
                raise ValueError(f"agent {agent!r}, task {task_id!r}: {exc}") from None
        self._agents[task_id] = agents
        self._sessions[task_id] = session
        if self._finalizer is None:
            self._finalizer = weakref.finalize(self, _close_all, self._sessions)
        return session

    # -- sending -----------------------------------------------------------------------

    def _env_action(self, action: Any, space: Any) -> Any:
        if self.normalize_actions:
            return unsquash_action(action, space)
        if self.clip_actions:
            return clip_action(action, space)
        return action

    def _send(self, rows: list[_Row], metrics: Any) -> None:
        if not rows:
            return
        by_task: dict[str, list[_Row]] = {}
        for row in rows:
            by_task.setdefault(row.slot.task_id, []).append(row)
        knn_sum = 0.0
        active = 0
        for task_rows in by_task.values():
            # One batch per task; an agent with several new steps (never, with RLlib's
            # EnvRunners: one call per env step) gets one batch per step, in order.
            while task_rows:
                batch: list[_Row] = []
                rest: list[_Row] = []
                seen: set[int] = set()
                for row in task_rows:
                    (rest if row.slot.env_id in seen else batch).append(row)
                    seen.add(row.slot.env_id)
                knn_sum, active = self._step(batch, knn_sum, active)
                task_rows = rest
        self._counts.agent_steps += len(rows)
        if metrics is not None:
            metrics.log_value(("tamrm", "knn_reward_mean"), knn_sum / len(rows), window=100)
            metrics.log_value(("tamrm", "knn_active_fraction"), active / len(rows), window=100)

    def _step(self, rows: list[_Row], knn_sum: float, active: int) -> tuple[float, int]:
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
                        self._env_action(r.action, r.sa_episode.action_space), dtype=np.float64
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
            _put(sa.rewards, row.index, shaped)
            info = dict(_item(sa.infos, row.index + 1) or {})
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
            _put(sa.infos, row.index + 1, info)
            if row.terminated or row.truncated:
                self._counts.episodes += 1
        knn_sum += float(result.knn_rewards.sum())
        active += int(result.knn_active.sum())
        return knn_sum, active


def _item(buf: Any, k: int) -> Any:
    """Item ``k`` (0: the first after the lookback) of an episode's InfiniteLookbackBuffer."""
    data = buf.data
    if isinstance(data, list):  # an episode being sampled: index its list directly
        return data[buf.lookback + k]
    return buf.get(k)


def _put(buf: Any, k: int, value: Any) -> None:
    """Overwrite item ``k`` of an episode's InfiniteLookbackBuffer."""
    if isinstance(buf.data, list):
        buf.data[buf.lookback + k] = value
    else:
        buf.set(new_data=value, at_indices=k)


#: The attributes starting with ``_`` that a pickled :class:`KnnShaping` keeps
#: (ConnectorV2's own).
_KEEP = frozenset(
    {
        "_observation_space",
        "_action_space",
        "_input_observation_space",
        "_input_action_space",
        "_ctor_kwargs",
    }
)


def _build_knn(
    env: Any = None,
    spaces: Any = None,
    device: Any = None,
    *,
    options: dict[str, Any],
) -> KnnShaping:
    num_envs = getattr(env, "num_envs", None) if env is not None else None
    return KnnShaping(**{"num_envs": num_envs, **options})


def knn_connector(task: TaskMap, **options: Any) -> Callable[..., KnnShaping]:
    """A builder for ``config.env_runners(env_to_module_connector=...)``.

    ``knn_connector(task, **options)(env, spaces, device)`` returns
    ``KnnShaping(task=task, num_envs=env.num_envs, **options)``; the builder pickles
    (RLlib sends it to every EnvRunner) when ``task`` does. To combine the piece with
    other env-to-module pieces, return a list with it first::

        env_to_module_connector=lambda env, spaces, device: [
            tamrm.rllib.knn_connector("cartpole")(env), FlattenObservations()]

    Raises:
        TypeError, ValueError: A bad ``task`` or option (checked here, on the driver).
    """
    options = {"task": task, **options}
    KnnShaping(**options)  # checks the options now rather than on every EnvRunner
    return functools.partial(_build_knn, options=options)


class PotentialShaping(ConnectorV2):  # type: ignore[misc]
    """Learner ConnectorV2 piece: adds ``beta * (gamma * V(s') - V(s))`` to the rewards.

    V is the learner's own module's value function (``ValueFunctionAPI.compute_values``,
    e.g. PPO's critic), evaluated on each episode chunk's observations with the weights
    of this update. ``V(s') = 0`` after a terminated step; after a truncated step, or at
    the end of a chunk cut mid-episode, V(s') is V of the real next observation (SPEC §4,
    the ``F`` a session computes from sent values). With ``gate_potential`` F counts only
    on steps whose kNN term was active (``knn_active`` in the infos :class:`KnnShaping`
    writes), as a task with ``gate_potential=True`` computes it.

    Add it with ``config.learners(learner_connector=potential_connector(...))``: RLlib
    puts custom learner pieces before its own, so the rewards it batches (and PPO's GAE
    reads) are the shaped ones. PPO's learner prepends one artificial bootstrap step to
    each chunk; it is recognised and left unshaped.

    Once only: the piece marks each chunk it shapes (``custom_data[POTENTIAL_MARK]``,
    the agent timesteps shaped; the mark survives pickling and is not inherited by the
    chunks RLlib cuts after it) and skips a chunk that carries its own mark, so episodes
    handed to the learner again, or a second piece, add nothing; a chunk shaped over a
    different span is an error rather than a second F. It never writes into the reward
    arrays it was given (a replay buffer's episodes may share them): the shaped rewards
    are a new array. Epochs and minibatches reuse the batch built once per update.

    Args:
        input_observation_space: As for every ConnectorV2 (unused).
        input_action_space: As for every ConnectorV2 (unused).
        beta: The weight beta of F.
        gamma: The discount gamma of F.
        gate_potential: Count F only where the kNN term was active.
        modules: Only shape the episodes of these module ids (``None``: every module).
            Modules without a value function are an error unless left out here.
    """

    def __init__(
        self,
        input_observation_space: Any = None,
        input_action_space: Any = None,
        *,
        beta: float,
        gamma: float,
        gate_potential: bool = False,
        modules: Collection[Hashable] | None = None,
    ) -> None:
        super().__init__(input_observation_space, input_action_space)
        for name, value in (("beta", beta), ("gamma", gamma)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name} must be a number, got {type(value).__name__}")
            if not np.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1] (SPEC §1.1), got {gamma}")
        if not isinstance(gate_potential, bool):
            raise TypeError(f"gate_potential must be a bool, got {type(gate_potential).__name__}")
        self.beta = float(beta)
        self.gamma = float(gamma)
        self.gate_potential = gate_potential
        self.modules = None if modules is None else frozenset(modules)

    def __call__(
        self,
        *,
        rl_module: Any,
        batch: dict[str, Any],
        episodes: list[Any],
        shared_data: dict[str, Any] | None = None,
        metrics: Any = None,
        **_: Any,
    ) -> Any:
        """Add beta * F to the rewards of every chunk in ``episodes`` not shaped yet."""
        if any(isinstance(v, Mapping) and Columns.REWARDS in v for v in batch.values()) or (
            Columns.REWARDS in batch
        ):
            raise RuntimeError(
                "PotentialShaping must come before RLlib's default learner pieces: the batch "
                "already holds the rewards (use config.learners(learner_connector=...))"
            )
        # PPO's AddOneTsToEpisodesAndTruncate ran first: the last step of every chunk is
        # an artificial one for bootstrapping.
        extra = int(bool(shared_data and shared_data.get("_added_loss_mask_for_valid_episode_ts")))
        todo: dict[Any, list[tuple[Any, int]]] = {}
        for sa in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            module_id = sa.module_id if sa.module_id is not None else DEFAULT_MODULE_ID
            if self.modules is not None and module_id not in self.modules:
                continue
            steps = len(sa) - extra
            if steps <= 0:
                continue
            span = (int(sa.t_started), int(sa.t_started) + steps)
            mark = sa.custom_data.get(POTENTIAL_MARK)
            if mark is not None and tuple(mark) == span:
                continue
            if mark is not None and mark[0] < span[1] and span[0] < mark[1]:
                raise RuntimeError(
                    f"episode {sa.id_!r} (agent {sa.agent_id!r}): its agent steps "
                    f"{mark[0]}..{mark[1] - 1} already carry beta * F, and this chunk spans "
                    f"{span[0]}..{span[1] - 1}; refusing to add F twice"
                )
            todo.setdefault(module_id, []).append((sa, steps))
        total = 0.0
        count = 0
        for module_id, items in todo.items():
            values = self._values(rl_module, module_id, items)
            offset = 0
            for sa, steps in items:
                v = values[offset : offset + steps + 1].copy()
                offset += steps + 1
                if sa.is_terminated:
                    v[steps] = 0.0
                potential = self.gamma * v[1:] - v[:-1]
                if self.gate_potential:
                    potential *= self._knn_active(sa, steps)
                shaped = self.beta * potential
                _add_rewards(sa, shaped)
                sa.custom_data[POTENTIAL_MARK] = (int(sa.t_started), int(sa.t_started) + steps)
                total += float(shaped.sum())
                count += steps
        if metrics is not None and count:
            metrics.log_value(("tamrm", "beta_potential_mean"), total / count, window=1)
        return batch

    def _values(
        self, rl_module: Any, module_id: Any, items: list[tuple[Any, int]]
    ) -> npt.NDArray[np.float64]:
        """V(o_0..o_n) of every chunk in ``items``, concatenated, from one forward pass."""
        import torch
        from ray.rllib.utils.torch_utils import convert_to_torch_tensor

        module = rl_module[module_id] if isinstance(rl_module, MultiRLModule) else rl_module
        if not isinstance(module, ValueFunctionAPI):
            raise TypeError(
                f"module {module_id!r} ({type(module).__name__}) has no value function "
                "(ValueFunctionAPI): PotentialShaping needs V(s); leave the module out "
                "with modules=..."
            )
        if module.is_stateful():
            raise NotImplementedError(
                f"module {module_id!r} is stateful (recurrent): PotentialShaping computes "
                "V(s) of stateless modules only"
            )
        parts = []
        for sa, steps in items:
            obs = sa.get_observations(slice(0, steps + 1))
            parts.append(batch_structs(obs) if isinstance(obs, list) else obs)
        obs_batch = tree.map_structure(lambda *xs: np.concatenate(xs, axis=0), *parts)
        params = list(module.parameters()) if hasattr(module, "parameters") else []
        device = params[0].device if params else None
        with torch.no_grad():
            tensor = convert_to_torch_tensor(obs_batch, device=device)
            out = module.compute_values({Columns.OBS: tensor})
        values = np.asarray(out.detach().cpu().numpy(), dtype=np.float64).reshape(-1)
        expected = sum(steps + 1 for _, steps in items)
        if values.shape[0] != expected:
            raise ValueError(
                f"module {module_id!r}: compute_values returned {values.shape[0]} values for "
                f"{expected} observations"
            )
        return values

    def _knn_active(self, sa: Any, steps: int) -> npt.NDArray[np.float64]:
        infos = sa.get_infos(slice(1, steps + 1))
        flags = np.zeros(steps, dtype=np.float64)
        for k, info in enumerate(infos):
            if "knn_active" not in info:
                raise ValueError(
                    f"gate_potential: step {sa.t_started + k} of episode {sa.id_!r} has no "
                    "'knn_active' info; the EnvRunners must run KnnShaping"
                )
            flags[k] = float(bool(info["knn_active"]))
        return flags


def _add_rewards(sa: Any, shaped: npt.NDArray[np.float64]) -> None:
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


def _build_potential(
    input_observation_space: Any = None,
    input_action_space: Any = None,
    device: Any = None,
    *,
    options: dict[str, Any],
) -> PotentialShaping:
    return PotentialShaping(input_observation_space, input_action_space, **options)


def potential_connector(
    task: Task | TaskConfig | None = None,
    *,
    beta: float | None = None,
    gamma: float | None = None,
    gate_potential: bool | None = None,
    modules: Collection[Hashable] | None = None,
) -> Callable[..., PotentialShaping]:
    """A builder for ``config.learners(learner_connector=...)``.

    ``beta``, ``gamma`` and ``gate_potential`` default to ``task``'s (a :class:`tamrm.Task`
    from ``client.get_task`` or its ``config``), so that F is the one the task would
    compute from sent values; without a task give ``beta`` and ``gamma``.

    Raises:
        TypeError, ValueError: Missing or bad values (checked here, on the driver).
    """
    config = task.config if isinstance(task, Task) else task
    if config is not None and not isinstance(config, TaskConfig):
        raise TypeError(f"task must be a tamrm.Task or TaskConfig, got {type(task).__name__}")
    if beta is None:
        if config is None:
            raise TypeError("potential_connector needs beta (or a task to take it from)")
        beta = config.beta
    if gamma is None:
        if config is None:
            raise TypeError("potential_connector needs gamma (or a task to take it from)")
        gamma = config.gamma
    if gate_potential is None:
        gate_potential = bool(config.gate_potential) if config is not None else False
    options: dict[str, Any] = {
        "beta": beta,
        "gamma": gamma,
        "gate_potential": gate_potential,
        "modules": None if modules is None else frozenset(modules),
    }
    PotentialShaping(**options)
    return functools.partial(_build_potential, options=options)


def _pieces(connector: Any) -> Iterable[Any]:
    """``connector`` and, for a pipeline, every piece in it (depth first)."""
    yield connector
    for child in getattr(connector, "connectors", None) or ():
        yield from _pieces(child)


def close_sessions(env_runner: Any) -> ShapingCounts:
    """Close the tamrm sessions of an EnvRunner's :class:`KnnShaping` pieces.

    For ``algo.env_runner_group.foreach_env_runner(tamrm.rllib.close_sessions)`` before
    ``algo.stop()``: a local session reports its last steps when it closes (RLlib stops
    its EnvRunner actors without closing their connectors). Returns what the pieces sent.
    """
    counts = ShapingCounts()
    for piece in _pieces(getattr(env_runner, "_env_to_module", None)):
        if isinstance(piece, KnnShaping):
            counts = counts + piece.close()
    return counts
