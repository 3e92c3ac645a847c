"""The EnvRunner side: :class:`KnnShaping` shapes the agent steps of every episode.

The piece tracks each sub-environment's episode (one per sub-environment, in order), gives
each (sub-environment, agent) a slot of its task's session, collects the agent steps
added since its last call (:mod:`tamrm.rllib._send` sends them) and abandons the episodes
RLlib drops. :func:`knn_connector` builds it on every EnvRunner; :func:`close_sessions`
closes an EnvRunner's pieces.
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core import DEFAULT_AGENT_ID
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.rllib.utils.spaces.space_utils import clip_action, unsquash_action

from tamrm._client import Client
from tamrm._connection import ConnectionOptions
from tamrm._errors import TamrmError
from tamrm._session import Session
from tamrm._wrapping import check_action_space
from tamrm.rllib._clients import process_client
from tamrm.rllib._episodes import item
from tamrm.rllib._send import Row, ShapingCounts, Slot, send_rows
from tamrm.rllib._tasks import TaskMap, check_task_map, task_of

__all__ = ["KnnShaping", "close_sessions", "knn_connector"]


@dataclass
class _EnvState:
    """What :class:`KnnShaping` knows about one sub-environment's current episode."""

    episode_id: str | None = None
    #: Per agent: the agent timestep up to which its steps are shaped (global ``t``).
    shaped: dict[Any, int] = field(default_factory=dict)
    #: Sum of the environment rewards of every agent in the episode so far (metrics).
    env_return: float = 0.0
    done: bool = False


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
        check_task_map(task)
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
        self._slots: dict[tuple[int, Any], Slot] = {}
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
        rows: list[Row] = []
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

    def _new_steps(self, index: int, episode: Any) -> list[Row]:
        """The agent steps of ``episode`` not yet shaped, as rows to send."""
        state = self._envs[index]
        rows: list[Row] = []
        for agent_id, sa in self._agent_episodes(episode):
            start = state.shaped.get(agent_id, sa.t_started)
            first = max(start - sa.t_started, 0)
            length = len(sa)
            if first >= length:
                continue
            slot = self._slot(index, agent_id, episode, sa)
            for k in range(first, length):
                last = k == length - 1 and sa.is_done
                reward = float(item(sa.rewards, k))
                state.env_return += reward
                score = None
                if last and self.score_key is not None:
                    info = item(sa.infos, k + 1)
                    if self.score_key in info:
                        score = float(info[self.score_key])
                rows.append(
                    Row(
                        slot,
                        sa,
                        k,
                        item(sa.actions, k),
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

    def _slot(self, index: int, agent_id: Any, episode: Any, sa: Any) -> Slot:
        slot = self._slots.get((index, agent_id))
        if slot is not None:
            return slot
        spaces = self._agent_spaces(episode)
        if agent_id not in spaces:
            raise ValueError(
                f"agent {agent_id!r} is not one of the env's possible agents "
                f"{list(spaces)}: KnnShaping gives each possible agent a session slot"
            )
        task_id = task_of(self.task, agent_id)
        session = self._session(task_id, spaces)
        agents = self._agents[task_id]
        slot = Slot(session, index * len(agents) + agents.index(agent_id), task_id)
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
        agents = [a for a in spaces if task_of(self.task, a) == task_id]
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

    def _send(self, rows: list[Row], metrics: Any) -> None:
        if not rows:
            return
        knn_sum, active = send_rows(rows, self._env_action, self._counts)
        if metrics is not None:
            metrics.log_value(("tamrm", "knn_reward_mean"), knn_sum / len(rows), window=100)
            metrics.log_value(("tamrm", "knn_active_fraction"), active / len(rows), window=100)


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
