"""The PettingZoo wrappers: :class:`ShapedParallel` and :class:`ShapedAEC`.

Both keep their sessions in a :class:`tamrm.pettingzoo._pools.Pools`; each turns its env's
steps into agent moves and writes the shaped rewards and info keys back.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pettingzoo.utils.env import AECEnv, ParallelEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper, BaseWrapper

from tamrm._client import Client
from tamrm._closing import Closing
from tamrm._engine import Engine
from tamrm._session import Session
from tamrm.pettingzoo._pools import AgentValueFn, Move, Pools, TaskMap, pools_from_state

__all__ = ["ShapedAEC", "ShapedParallel"]


class _Shaped(Closing):
    """What both wrappers share: their sessions, pickling and closing."""

    env: Any
    _pools: Pools

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
        self._pools = Pools(env, api, task, values, score_key, local)
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
        self._pools = pools_from_state(self.env, state)
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
        moves: list[Move] = []
        for agent, action in actions.items():
            if agent not in live or agent in self._ended or agent not in rewards:
                continue
            terminated = bool(terminations.get(agent, False))
            truncated = bool(truncations.get(agent, False))
            move = Move(agent, action, float(rewards[agent]), terminated, truncated)
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
            move = Move(
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
