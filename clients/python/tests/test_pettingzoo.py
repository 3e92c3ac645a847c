"""tamrm.pettingzoo: the Parallel and AEC wrappers against one-env sessions, real envs, SuperSuit.

The property tests run a small random env twice in lockstep, wrapped and unwrapped, and
feed each agent's own actions, rewards and ends (from the unwrapped run) to a one-env
session of a task of its own: the wrapped run's rewards must be those, to the bit.
"""

from __future__ import annotations

import contextlib
import copy
import pickle
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tamrm
from tamrm.gym import INFO_KEYS

pytest.importorskip("pettingzoo")
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.test import api_test, parallel_api_test

from tamrm.pettingzoo import ShapedAEC, ShapedParallel

# Small pools that fill at once, the kNN term active from step 0: every step is shaped
# against a pool that the agents' own episodes keep changing.
POOL = {"pool_capacity": 2, "k": 2, "min_pool_size": 1, "start_step": 0, "gamma": 0.9}


# -- two tiny deterministic random envs ---------------------------------------------------


def _spaces(n_agents: int, num_actions: int, action_dim: int) -> tuple[list[str], Any, Any]:
    agents = [f"a{i}" for i in range(n_agents)]
    obs = spaces.Box(-100.0, 100.0, (2,), np.float64)
    act: spaces.Space[Any] = (
        spaces.Discrete(num_actions)
        if num_actions
        else spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
    )
    return agents, obs, act


def _lives(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per agent: the step it appears at (agent 0 at reset), its end, truncated or not."""
    spawn = rng.integers(0, 3, n)
    spawn[0] = 0
    end = spawn + rng.integers(1, 8, n)
    return spawn, end, rng.random(n) < 0.3


def _action_value(action: Any) -> float:
    return float(np.sum(np.asarray(action, dtype=np.float64)))


class RandomParallel(ParallelEnv[str, Any, Any]):
    """Agents appear at random steps and end (terminate or truncate) at random steps;
    every live agent gets a random reward each step, and an ending agent an episode
    score in its info."""

    metadata = {"name": "random_parallel_v0"}  # noqa: RUF012
    render_mode = None

    def __init__(
        self, n_agents: int = 3, num_actions: int = 3, action_dim: int = 0, spawns: bool = True
    ) -> None:
        self.possible_agents, self._obs_space, self._act_space = _spaces(
            n_agents, num_actions, action_dim
        )
        self.agents: list[str] = []
        self._spawns = spawns

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space[Any]:
        return self._act_space

    def _observe(self, agent: str) -> np.ndarray:
        return np.array([self.t * 0.5, self._rng.normal()], dtype=np.float64)

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
        self._rng = np.random.default_rng(seed)
        self.t = 0
        self._spawn, self._end, self._trunc = _lives(self._rng, len(self.possible_agents))
        if not self._spawns:
            self._end -= self._spawn
            self._spawn[:] = 0
        self.agents = [a for i, a in enumerate(self.possible_agents) if self._spawn[i] == 0]
        return {a: self._observe(a) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        self.t += 1
        live = list(self.agents)
        rewards = {
            a: round(float(self._rng.normal()), 3) + 0.25 * _action_value(actions.get(a, 0))
            for a in live
        }
        index = {a: i for i, a in enumerate(self.possible_agents)}
        terms = {a: bool(self._end[index[a]] <= self.t and not self._trunc[index[a]]) for a in live}
        truncs = {a: bool(self._end[index[a]] <= self.t and self._trunc[index[a]]) for a in live}
        infos: dict[str, dict[str, Any]] = {
            a: {"score": float(index[a] + self.t)} if terms[a] or truncs[a] else {} for a in live
        }
        born = [a for i, a in enumerate(self.possible_agents) if self._spawn[i] == self.t]
        for a in born:
            rewards[a], terms[a], truncs[a], infos[a] = 0.0, False, False, {}
        self.agents = [a for a in live if not (terms[a] or truncs[a])] + born
        obs = {a: self._observe(a) for a in [*live, *born]}
        return obs, rewards, terms, truncs, infos


class RandomAEC(AECEnv[str, Any, Any]):
    """Turn-based: every turn gives each live agent a random reward (so an agent's
    ``last()`` reward sums several), agents appear and end at random turns."""

    metadata = {"name": "random_aec_v0"}  # noqa: RUF012

    def __init__(self, n_agents: int = 3, num_actions: int = 3, action_dim: int = 0) -> None:
        super().__init__()
        self.possible_agents, self._obs_space, self._act_space = _spaces(
            n_agents, num_actions, action_dim
        )

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space[Any]:
        return self._act_space

    def observe(self, agent: str) -> np.ndarray:
        return np.array([self.turn * 0.5, self.possible_agents.index(agent)], dtype=np.float64)

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        self._rng = np.random.default_rng(seed)
        self.turn = 0
        self._spawn, self._end, self._trunc = _lives(self._rng, len(self.possible_agents))
        self._end = self._end * 2  # turns, not steps: let agents act a few times
        self.agents = [a for i, a in enumerate(self.possible_agents) if self._spawn[i] == 0]
        self.rewards = dict.fromkeys(self.agents, 0.0)
        self._cumulative_rewards = dict.fromkeys(self.agents, 0.0)
        self.terminations = dict.fromkeys(self.agents, False)
        self.truncations = dict.fromkeys(self.agents, False)
        self.infos = {a: {} for a in self.agents}
        self.agent_selection = self.agents[0]

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._was_dead_step(action)
            return
        self._cumulative_rewards[agent] = 0.0
        self.turn += 1
        for a in self.agents:
            bonus = 0.25 * _action_value(action) if a == agent else 0.0
            self.rewards[a] = round(float(self._rng.normal()), 3) + bonus
        for i, a in enumerate(self.possible_agents):
            if a in self.agents and self._end[i] <= self.turn:
                self.terminations[a] = not bool(self._trunc[i])
                self.truncations[a] = bool(self._trunc[i])
                self.infos[a] = {"score": float(i + self.turn)}
            if self._spawn[i] == self.turn and a not in self.agents:
                self.agents.append(a)
                self.rewards[a] = self._cumulative_rewards[a] = 0.0
                self.terminations[a] = self.truncations[a] = False
                self.infos[a] = {}
        self._accumulate_rewards()
        live = [a for a in self.agents if not (self.terminations[a] or self.truncations[a])]
        order = self.agents.index(agent)
        later = [a for a in self.agents[order + 1 :] + self.agents[: order + 1] if a in live]
        self.agent_selection = later[0] if later else agent
        self._deads_step_first()

    def close(self) -> None:
        pass

    def render(self) -> None:
        pass


# -- helpers ------------------------------------------------------------------------------


def _make_tasks(api: Any, ids: list[str], num_actions: int, action_dim: int) -> None:
    space = {"num_actions": num_actions} if num_actions else {"action_dim": action_dim}
    for task_id in ids:
        api.create_task(task_id, beta=0.5, **space, **POOL)  # type: ignore[arg-type]


def _value_fn(kind: str | None, num_actions: int) -> Callable[[Any, Any], Any] | None:
    if kind is None:
        return None
    if kind == "v":
        return lambda agent, obs: 0.3 * float(obs[0]) - 0.1 * float(obs[1]) + len(agent)
    return lambda agent, obs: np.arange(num_actions) * float(obs[0]) - float(obs[1])


class Reference:
    """A one-env session per agent (on a task of its own) fed that agent's moves."""

    def __init__(self, api: Any, prefix: str, agents: list[str], values: Any) -> None:
        self.sessions = {a: api.session(f"{prefix}/{a}", 1) for a in agents}
        self.values = values

    def shape(
        self,
        agent: str,
        action: Any,
        reward: float,
        ended: tuple[bool, bool],
        obs: Any,
        info: dict[str, Any],
    ) -> float:
        session = self.sessions[agent]
        kwargs: dict[str, Any] = {}
        if any(ended) and "score" in info:
            kwargs["episode_scores"] = {0: info["score"]}
        if self.values is not None:
            v, nv = self.values(agent, obs[0]), self.values(agent, obs[1])
            key = "q_values" if np.ndim(v) else "values"
            kwargs.update({key: [v], f"next_{key}": [nv]})
        act = [int(action)] if session.config.discrete else [np.asarray(action)]
        result = session.step(act, [reward], [ended[0]], [ended[1]], **kwargs)
        return float(result.rewards[0])

    def reset(self) -> None:
        for session in self.sessions.values():
            if session.episodes_in_progress[0]:
                session.abandon([0])

    def close(self) -> None:
        for session in self.sessions.values():
            session.close()


@pytest.fixture
def prefix(client: Any) -> Iterator[str]:
    """A unique task-id prefix; the tasks under it are deleted afterwards."""
    name = f"t/pz/{uuid.uuid4().hex[:10]}"
    yield name
    _delete_under(client, name)


def _stats_sum(api: Any, ids: list[str]) -> tuple[int, int]:
    stats = [api.get_task(t).stats for t in ids]
    return sum(s.episodes_completed for s in stats), sum(s.steps_shaped for s in stats)


@contextlib.contextmanager
def _twins(client: Any, run: dict[str, Any], wrapper: Any, env_class: Any) -> Iterator[Any]:
    """A wrapped env (a task per agent), its unwrapped twin, the reference, a policy RNG."""
    num_actions, action_dim = (0, 2) if run["continuous"] else (3, 0)
    kind = None if run["continuous"] and run["values"] == "q" else run["values"]
    values = _value_fn(kind, num_actions)
    prefix = f"t/pz-twins/{uuid.uuid4().hex[:10]}"
    agents = [f"a{i}" for i in range(run["n_agents"])]
    _make_tasks(client, [f"{prefix}/w/{a}" for a in agents], num_actions, action_dim)
    _make_tasks(client, [f"{prefix}/r/{a}" for a in agents], num_actions, action_dim)
    env = wrapper(
        env_class(run["n_agents"], num_actions, action_dim),
        client,
        lambda agent: f"{prefix}/w/{agent}",
        values=values,
        score_key="score",
    )
    raw = env_class(run["n_agents"], num_actions, action_dim)
    ref = Reference(client, f"{prefix}/r", agents, values)
    try:
        yield env, raw, ref, np.random.default_rng(run["seed"]), num_actions, action_dim
    finally:
        env.close()
        ref.close()
        _delete_under(client, prefix)


def _delete_under(client: Any, prefix: str) -> None:
    for task in client.list_tasks():
        if task.task_id.startswith(prefix + "/"):
            client.delete_task(task.task_id)


# -- exactness: Parallel ------------------------------------------------------------------

runs = st.fixed_dictionaries(
    {
        "seed": st.integers(0, 2**16),
        "n_agents": st.integers(1, 4),
        "continuous": st.booleans(),
        "values": st.sampled_from([None, "v", "q"]),
        # Steps before each reset (an episode cut short is abandoned).
        "episodes": st.lists(st.integers(1, 10), min_size=1, max_size=4),
    }
)


@settings(max_examples=20, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(run=runs)
def test_parallel_equals_one_env_session_per_agent(client: Any, run: dict[str, Any]) -> None:
    with _twins(client, run, ShapedParallel, RandomParallel) as twins:
        env, raw, ref, policy, num_actions, action_dim = twins
        for episode, steps in enumerate(run["episodes"]):
            seed = run["seed"] + episode
            env.reset(seed=seed)
            raw_obs, _ = raw.reset(seed=seed)
            ref.reset()
            for _ in range(steps):
                if not raw.agents:
                    break
                actions = {
                    a: policy.integers(num_actions)
                    if num_actions
                    else policy.uniform(-1, 1, action_dim).astype(np.float32)
                    for a in raw.agents
                }
                before = dict(raw_obs)
                shaped_step = env.step(actions)
                raw_step = raw.step(actions)
                raw_obs = {**raw_obs, **raw_step[0]}
                _, rewards, terms, truncs, infos = shaped_step
                for a in actions:
                    reward = float(raw_step[1][a])
                    ended = (terms[a], truncs[a])
                    pair = (before[a], raw_step[0][a])
                    want = ref.shape(a, actions[a], reward, ended, pair, raw_step[4][a])
                    assert rewards[a] == want, (a, rewards[a], want)
                    assert infos[a]["original_reward"] == reward
                    assert set(INFO_KEYS) <= set(infos[a])
                # Agents that appeared on this step keep the env's reward, no shaping keys.
                for a in set(rewards) - set(actions):
                    assert rewards[a] == raw_step[1][a]
                    assert "original_reward" not in infos[a]


# -- exactness: AEC -----------------------------------------------------------------------


def _play_aec(
    env: Any,
    raw: RandomAEC,
    ref: Reference | None,
    policy: np.random.Generator,
    turns: int,
    seed: int,
    num_actions: int,
    action_dim: int,
) -> tuple[int, int]:
    """Play ``turns`` turns of both in lockstep; returns (agent-steps, agent-episodes).

    The wrapper shapes an agent's earlier action when a step selects the agent again, so
    the reference is fed then too, and ``last()`` at that turn must report its answer.
    """
    env.reset(seed=seed)
    raw.reset(seed=seed)
    if ref is not None:
        ref.reset()
    last: dict[str, tuple[Any, Any]] = {}  # agent -> (action, obs) of its last turn
    steps = ends = 0
    shaped: tuple[float | None] | None = None  # at this turn: (the reference's reward,)
    for _ in range(turns):
        if not raw.agents:
            break
        agent = raw.agent_selection
        assert env.agent_selection == agent
        _, reward, term, trunc, info = env.last()
        raw_obs, raw_reward, raw_term, raw_trunc, _ = raw.last()
        assert (term, trunc) == (raw_term, raw_trunc)
        if shaped is not None:
            if shaped[0] is not None:
                assert reward == shaped[0], (agent, reward, shaped[0])
            assert info["original_reward"] == raw_reward
            assert set(INFO_KEYS) <= set(info)
        else:
            assert reward == raw_reward
            assert "original_reward" not in info
        if term or trunc:
            action = None
        elif num_actions:
            action = int(policy.integers(num_actions))
        else:
            action = policy.uniform(-1, 1, action_dim).astype(np.float32)
        if action is not None:
            last[agent] = (action, raw_obs)
        env.step(action)
        raw.step(action)
        shaped = None
        if raw.agents and raw.agent_selection in last:
            agent = raw.agent_selection
            action, before = last.pop(agent)
            after, raw_reward, term, trunc, raw_info = raw.last()
            steps += 1
            ends += term or trunc
            want = None
            if ref is not None:
                pair = (before, after)
                want = ref.shape(agent, action, raw_reward, (term, trunc), pair, raw_info)
            shaped = (want,)
    return steps, ends


@settings(max_examples=20, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(run=runs)
def test_aec_equals_one_env_session_per_agent(client: Any, run: dict[str, Any]) -> None:
    with _twins(client, run, ShapedAEC, RandomAEC) as twins:
        env, raw, ref, policy, num_actions, action_dim = twins
        for episode, turns in enumerate(run["episodes"]):
            seed = run["seed"] + episode
            _play_aec(env, raw, ref, policy, 3 * turns, seed, num_actions, action_dim)


# -- a shared task counts every agent-step and agent-episode ------------------------------


@settings(max_examples=10, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**16), n_agents=st.integers(1, 4))
def test_shared_task_counts_every_agent_step_and_episode(
    client: Any, seed: int, n_agents: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    prefix = f"t/pz-shared/{uuid.uuid4().hex[:10]}"
    _make_tasks(client, [f"{prefix}/par", f"{prefix}/aec"], 3, 0)
    par = ShapedParallel(RandomParallel(n_agents), client, f"{prefix}/par")
    aec = ShapedAEC(RandomAEC(n_agents), client, f"{prefix}/aec")
    calls: list[tamrm.Session] = []
    step = tamrm.Session.step

    def counting(self: tamrm.Session, *args: Any, **kwargs: Any) -> Any:
        calls.append(self)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(tamrm.Session, "step", counting)
    policy = np.random.default_rng(seed)
    try:
        # Parallel: one call per step (one task), a row per agent that acted.
        want_steps = want_ends = 0
        for episode in range(3):
            par.reset(seed=seed + episode)
            while par.agents:
                calls.clear()
                acting = list(par.agents)
                _, _, terms, truncs, _ = par.step({a: policy.integers(3) for a in acting})
                assert calls == [par.sessions[f"{prefix}/par"]]
                want_steps += len(acting)
                want_ends += sum(terms[a] or truncs[a] for a in acting)
        assert _stats_sum(client, [f"{prefix}/par"]) == (want_ends, want_steps)
        # AEC: a step per agent turn that completes an earlier action.
        raw = RandomAEC(n_agents)
        want_steps = want_ends = 0
        for episode in range(3):
            steps, ends = _play_aec(aec, raw, None, policy, 200, seed + episode, 3, 0)
            want_steps += steps
            want_ends += ends
            assert not raw.agents
        assert _stats_sum(client, [f"{prefix}/aec"]) == (want_ends, want_steps)
    finally:
        par.close()
        aec.close()
        for task_id in (f"{prefix}/par", f"{prefix}/aec"):
            client.delete_task(task_id)


def test_parallel_one_step_call_per_task(
    client: Any, prefix: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Four agents on two teams: two calls a step, whatever the number of agents."""
    _make_tasks(client, [f"{prefix}/even", f"{prefix}/odd"], 3, 0)
    env = ShapedParallel(
        RandomParallel(4),
        client,
        lambda agent: f"{prefix}/even" if int(agent[1:]) % 2 == 0 else f"{prefix}/odd",
    )
    assert [s.num_envs for s in env.sessions.values()] == [2, 2]
    seen: list[tuple[str, int]] = []
    step = tamrm.Session.step

    def counting(self: tamrm.Session, actions: Any, *args: Any, **kwargs: Any) -> Any:
        seen.append((self.task_id, len(actions)))
        return step(self, actions, *args, **kwargs)

    monkeypatch.setattr(tamrm.Session, "step", counting)
    with env:
        for seed in range(5):
            env.reset(seed=seed)
            while env.agents:
                seen.clear()
                acting = list(env.agents)
                env.step(dict.fromkeys(acting, 1))
                teams = {"even" if int(a[1:]) % 2 == 0 else "odd" for a in acting}
                assert sorted(t.rsplit("/", 1)[1] for t, _ in seen) == sorted(teams)
                assert sum(n for _, n in seen) == len(acting)


# -- reset, close, errors -----------------------------------------------------------------


def test_reset_mid_episode_abandons(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/t"], 3, 0)
    env = ShapedParallel(RandomParallel(3), client, f"{prefix}/t")
    env.reset(seed=1)
    env.step(dict.fromkeys(env.agents, 0))
    (session,) = env.sessions.values()
    assert session.episodes_in_progress.any()
    before = client.get_task(f"{prefix}/t").stats
    env.reset(seed=2)
    assert not session.episodes_in_progress.any()
    env.step(dict.fromkeys(env.agents, 0))
    after = client.get_task(f"{prefix}/t").stats
    assert after.pool_version == before.pool_version
    assert after.episodes_completed == before.episodes_completed
    env.close()


class VanishingAEC(RandomAEC):
    """RandomAEC whose last agent is taken out of ``agents`` after ``vanish_at`` turns
    without a termination or truncation (as some envs remove a captured piece)."""

    vanish_at = 4

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        super().reset(seed, options)
        # Everybody from the start, nobody ends: the only way out is the removal.
        self._end[:] = 10_000
        for a in self.possible_agents[len(self.agents) :]:
            self.agents.append(a)
            self.rewards[a] = self._cumulative_rewards[a] = 0.0
            self.terminations[a] = self.truncations[a] = False
            self.infos[a] = {}

    def step(self, action: Any) -> None:
        super().step(action)
        gone = self.possible_agents[-1]
        if self.turn >= self.vanish_at and gone in self.agents and len(self.agents) > 1:
            self.agents.remove(gone)
            for table in (
                self.rewards,
                self._cumulative_rewards,
                self.terminations,
                self.truncations,
                self.infos,
            ):
                table.pop(gone, None)
            if self.agent_selection == gone:
                self.agent_selection = self.agents[0]


def test_aec_agent_removed_without_an_end_abandons_its_episode(client: Any, prefix: str) -> None:
    """An agent the env removes without ending it stores nothing: its episode is
    abandoned (SPEC §12), the other agents go on being shaped."""
    raw = VanishingAEC(2, 3, 0)
    ids = [f"{prefix}/{a}" for a in raw.possible_agents]
    _make_tasks(client, ids, 3, 0)
    env = ShapedAEC(raw, client, lambda agent: f"{prefix}/{agent}")
    env.reset(seed=0)
    gone = raw.possible_agents[-1]
    assert gone in env.agents
    turns = 0
    while gone in env.agents or turns < 2 * raw.vanish_at:
        env.step(0)
        turns += 1
        assert turns < 50
    assert gone not in env.agents
    session = env.sessions[f"{prefix}/{gone}"]
    assert not session.episodes_in_progress.any(), "the removed agent's episode is abandoned"
    stats = client.get_task(f"{prefix}/{gone}").stats
    assert stats.episodes_completed == 0
    assert stats.pool_size == 0
    # The agent left goes on, shaped.
    _, _, _, _, info = env.last()
    assert set(INFO_KEYS) <= set(info)
    env.close()


def test_close_closes_the_sessions_it_opened(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/a", f"{prefix}/b"], 3, 0)
    env = ShapedAEC(RandomAEC(2), client, lambda a: f"{prefix}/{'a' if a == 'a0' else 'b'}")
    sessions = list(env.sessions.values())
    assert len(sessions) == 2 and not any(s.closed for s in sessions)
    env.close()
    assert all(s.closed for s in sessions)
    client.get_task(f"{prefix}/a")  # the api stays open


def test_missing_task_names_it_and_its_agents(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/a0"], 3, 0)
    with pytest.raises(tamrm.TaskNotFound, match=rf"{prefix}/a1.*'a1', 'a2'"):
        ShapedParallel(
            RandomParallel(3), client, lambda a: f"{prefix}/{'a0' if a == 'a0' else 'a1'}"
        )


def test_action_space_mismatch_names_agent_and_task(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/five"], 5, 0)
    with pytest.raises(ValueError, match=rf"agent 'a0', task '{prefix}/five'.*num_actions=5"):
        ShapedAEC(RandomAEC(2), client, f"{prefix}/five")
    _make_tasks(client, [f"{prefix}/box"], 0, 3)
    with pytest.raises(ValueError, match=rf"agent 'a0', task '{prefix}/box'.*action_dim=3"):
        ShapedParallel(RandomParallel(2, 0, 2), client, f"{prefix}/box")


def test_bad_task_map(client: Any, prefix: str) -> None:
    with pytest.raises(TypeError, match=r"task\('a0'\) returned int"):
        ShapedParallel(RandomParallel(2), client, lambda a: 7)  # type: ignore[arg-type,return-value]
    with pytest.raises(TypeError, match="task must be a task id"):
        ShapedParallel(RandomParallel(2), client, 7)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="api must be"):
        ShapedParallel(RandomParallel(2), "127.0.0.1:1", prefix)  # type: ignore[arg-type]


def test_values_of_different_shapes_are_rejected(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/t"], 3, 0)
    env = ShapedParallel(
        RandomParallel(2, spawns=False),
        client,
        f"{prefix}/t",
        values=lambda agent, obs: 1.0 if agent == "a0" else [1.0, 2.0, 3.0],
    )
    env.reset(seed=0)
    with pytest.raises(ValueError, match="rows of different shapes"):
        env.step(dict.fromkeys(env.agents, 0))
    env.close()


# -- real environments: PettingZoo's API tests through the wrappers ----------------------


def test_api_tests_on_random_envs(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/t"], 3, 0)
    values = _value_fn("v", 3)
    env = ShapedAEC(RandomAEC(4), client, f"{prefix}/t", values=values)
    api_test(env, num_cycles=300)
    env.close()
    par = ShapedParallel(RandomParallel(4), client, f"{prefix}/t", values=values)
    parallel_api_test(par, num_cycles=300)
    par.close()


def test_mpe_simple_spread(client: Any, prefix: str) -> None:
    mpe2 = pytest.importorskip("mpe2")
    from mpe2 import simple_spread_v3

    _make_tasks(client, [f"{prefix}/spread"], 5, 0)
    _make_tasks(client, [f"{prefix}/box"], 0, 5)

    def v(agent: str, obs: np.ndarray) -> float:
        return float(np.sum(obs))

    assert mpe2 is not None
    for continuous, task in ((False, f"{prefix}/spread"), (True, f"{prefix}/box")):
        for wrapper, make, check in (
            (ShapedParallel, simple_spread_v3.parallel_env, parallel_api_test),
            (ShapedAEC, simple_spread_v3.env, api_test),
        ):
            env = make(N=3, max_cycles=25, continuous_actions=continuous)
            with wrapper(env, client, task, values=v) as wrapped:
                check(wrapped, num_cycles=30)
            stats = client.get_task(task).stats
            if wrapper is ShapedParallel:
                # Two episodes of 25 steps (then every agent is truncated) of 3 agents.
                assert (stats.episodes_completed, stats.steps_shaped) == (6, 150)
            else:
                # api_test plays one episode to its end (3 agent-episodes), then shorter runs.
                assert stats.episodes_completed >= 9


def test_mpe_speaker_listener_one_task_per_role(client: Any, prefix: str) -> None:
    pytest.importorskip("mpe2")
    from mpe2 import simple_speaker_listener_v4

    client.create_task(f"{prefix}/speaker", num_actions=3)
    client.create_task(f"{prefix}/listener", num_actions=5)

    def role(agent: str) -> str:
        return f"{prefix}/{agent.split('_')[0]}"

    par = ShapedParallel(simple_speaker_listener_v4.parallel_env(max_cycles=10), client, role)
    parallel_api_test(par, num_cycles=20)
    par.close()
    aec = ShapedAEC(simple_speaker_listener_v4.env(max_cycles=10), client, role)
    api_test(aec, num_cycles=20)
    aec.close()
    for r in ("speaker", "listener"):
        assert client.get_task(f"{prefix}/{r}").stats.episodes_completed >= 2
    # One pool for both roles does not fit their action spaces: the error names the agent.
    with pytest.raises(ValueError, match=rf"agent 'listener_0', task '{prefix}/speaker'"):
        ShapedParallel(simple_speaker_listener_v4.parallel_env(), client, f"{prefix}/speaker")


@pytest.mark.parametrize("game", ["tictactoe_v3", "connect_four_v3"])
def test_classic_turn_based_games(client: Any, prefix: str, game: str) -> None:
    pytest.importorskip("pygame")
    import importlib

    module = importlib.import_module(f"pettingzoo.classic.{game}")
    env = module.env()
    n = int(env.action_space(env.possible_agents[0]).n)
    client.create_task(f"{prefix}/{game}", num_actions=n, **POOL)

    def v(agent: str, obs: dict[str, np.ndarray]) -> np.ndarray:
        # Q(s, .) row from the board; illegal moves are masked.
        return obs["action_mask"] * float(np.sum(obs["observation"]))

    wrapped = ShapedAEC(env, client, f"{prefix}/{game}", values=v)
    api_test(wrapped, num_cycles=200)
    # A full game: the winner's and the loser's last moves end their episodes at the
    # turns on which they are removed, with their own ±1.
    wrapped.reset(seed=3)
    finals = {}
    for agent in wrapped.agent_iter():
        _, reward, term, trunc, info = wrapped.last()
        if term or trunc:
            finals[agent] = (info["original_reward"], reward)
            wrapped.step(None)
        else:
            wrapped.step(int(np.flatnonzero(wrapped.observe(agent)["action_mask"])[0]))
    assert set(finals) == set(wrapped.possible_agents)
    wrapped.close()


# -- copies: pickle, deepcopy, SuperSuit --------------------------------------------------


def test_pickle_reopens_sessions(client: Any, prefix: str) -> None:
    _make_tasks(client, [f"{prefix}/t"], 3, 0)
    env = ShapedParallel(RandomParallel(3), client, f"{prefix}/t", score_key="score")
    for copied in (pickle.loads(pickle.dumps(env)), copy.deepcopy(env)):
        old, new = env.sessions[f"{prefix}/t"], copied.sessions[f"{prefix}/t"]
        assert new is not old and not new.closed and new.num_envs == 3
        assert copied._pools.score_key == "score"
        copied.reset(seed=0)
        copied.step(dict.fromkeys(copied.agents, 1))
        assert new.episode_steps.sum() > 0 and old.episode_steps.sum() == 0
        copied.close()
        assert new.closed and not old.closed
    env.close()


def test_engine_wrapper_copies_in_its_process_only(engine: tamrm.Engine, tmp_path: Any) -> None:
    task = f"t/pz-engine/{uuid.uuid4().hex[:8]}"
    engine.create_task(task, num_actions=3)
    env = ShapedAEC(RandomAEC(2), engine, task)
    data = pickle.dumps(env)
    copied = pickle.loads(data)
    assert copied._pools.api is engine
    assert copied.sessions[task] is not env.sessions[task]
    copied.close()
    # Another process: a clear error (RandomAEC is importable there from this folder).
    path = tmp_path / "env.pkl"
    path.write_bytes(data)
    code = f"import pickle, sys; sys.path.insert(0, {str(__file__.rsplit('/', 1)[0])!r}); "
    code += f"pickle.loads(open({str(path)!r}, 'rb').read())"
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode != 0
    assert "a tamrm.Engine lives in one process" in proc.stderr, proc.stderr
    env.close()
    engine.delete_task(task)


def test_supersuit_parameter_sharing(remote_client: tamrm.Client, engine: tamrm.Engine) -> None:
    """SuperSuit copies the wrapped env by pickling it: in worker processes (a Client)
    and in this process (an Engine, too); every copy shapes on its own sessions."""
    ss = pytest.importorskip("supersuit")
    pytest.importorskip("mpe2")
    pytest.importorskip("stable_baselines3")
    from mpe2 import simple_spread_v3

    for api, cpus in ((remote_client, 2), (engine, 0)):
        task = f"t/pz-ss/{uuid.uuid4().hex[:8]}"
        api.create_task(task, num_actions=5)
        env = ShapedParallel(simple_spread_v3.parallel_env(N=3, max_cycles=10), api, task)
        venv = ss.pettingzoo_env_to_vec_env_v1(env)
        venv = ss.concat_vec_envs_v1(venv, 2, num_cpus=cpus, base_class="stable_baselines3")
        assert venv.num_envs == 6
        venv.reset()
        for _ in range(25):
            venv.step(np.random.randint(5, size=6))
        venv.close()
        env.close()
        stats = api.get_task(task).stats
        # 25 steps of 2 copies x 3 agents; an episode is 10 steps: 2 x 3 x 2 ended.
        assert stats.steps_shaped == 150
        assert stats.episodes_completed == 12
        api.delete_task(task)


def test_black_death_outside_sends_only_live_agents(engine: tamrm.Engine) -> None:
    """Shaping, then SuperSuit's black-death padding: a dead agent's padded steps (zero
    observation, zero reward) never reach the pool, and its end is its own."""
    ss = pytest.importorskip("supersuit")
    task = f"t/pz-bd/{uuid.uuid4().hex[:8]}"
    engine.create_task(task, num_actions=3)
    raw = RandomParallel(4, spawns=False)
    venv = ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(ShapedParallel(raw, engine, task)))
    live_steps = deaths = 0
    for seed in range(4):
        venv.reset(seed=seed)
        for _ in range(10):  # every agent ends within 8 steps
            live = set(raw.agents)
            _, rewards, _, _, infos = venv.step(np.ones(4, dtype=np.int64))
            shaped = {
                a
                for a, info in zip(raw.possible_agents, infos, strict=True)
                if "original_reward" in info
            }
            assert shaped == live
            live_steps += len(live)
            deaths += len(live - set(raw.agents))
            for i, agent in enumerate(raw.possible_agents):
                if agent not in live:
                    assert rewards[i] == 0
    stats = engine.get_task(task).stats
    assert (stats.steps_shaped, stats.episodes_completed) == (live_steps, deaths)
    assert deaths >= 16  # each seed's agents all end (SuperSuit may reset and go on)
    engine.delete_task(task)


def test_local_sessions(remote_client: tamrm.Client) -> None:
    task = f"t/pz-local/{uuid.uuid4().hex[:8]}"
    remote_client.create_task(task, num_actions=3)
    env = ShapedParallel(RandomParallel(3, spawns=False), remote_client, task, local=True)
    assert env.sessions[task].local
    copied = pickle.loads(pickle.dumps(env))
    assert copied.sessions[task].local
    copied.reset(seed=0)
    _, _, _, _, infos = copied.step(dict.fromkeys(copied.agents, 2))
    assert all("knn_reward" in info for info in infos.values())
    copied.close()
    env.close()
    remote_client.delete_task(task)
