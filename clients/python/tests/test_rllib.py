"""Ray RLlib (new API stack): ``tamrm.rllib.KnnShaping`` on EnvRunners, ``PotentialShaping``
on learners. Against the real server binary, with RLlib's own EnvRunners and learners:

- every agent step RLlib records is shaped exactly as a one-env session fed that agent's
  own actions, rewards and ends would shape it (random multi-agent envs whose agents join
  late, die early, observe every other step; a single-agent env; discrete and continuous
  actions, the latter as the env received them), on the task the agent maps to, and every
  agent step and agent episode reaches the server's statistics once;
- a reset in the middle of episodes abandons them; the next steps start at t = 0;
- the connector, its builder and a whole PPO config pickle, and the copies shape;
- the learner piece adds beta * (gamma * V(s') - V(s)) with the module's own critic once
  per chunk: not again on the same episodes, after a pickle round trip, or through a
  second piece, never into arrays a replay buffer shares, and once per PPO update with
  several epochs and minibatches (checked against V computed beside it);
- bad input gets an error naming the agent, task or module.
"""

from __future__ import annotations

import itertools
import os
import pickle
import re
import subprocess
import sys
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("ray.rllib")
torch = pytest.importorskip("torch")

import cloudpickle  # noqa: E402
import ray  # noqa: E402
from conftest import REPO_ROOT  # noqa: E402
from ray.rllib.algorithms.ppo import PPOConfig  # noqa: E402
from ray.rllib.connectors.connector_v2 import ConnectorV2  # noqa: E402
from ray.rllib.connectors.learner import AddOneTsToEpisodesAndTruncate  # noqa: E402
from ray.rllib.core import DEFAULT_AGENT_ID, DEFAULT_MODULE_ID  # noqa: E402
from ray.rllib.core.columns import Columns  # noqa: E402
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec  # noqa: E402
from ray.rllib.env.multi_agent_env import MultiAgentEnv  # noqa: E402
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner  # noqa: E402
from ray.rllib.env.single_agent_env_runner import SingleAgentEnvRunner  # noqa: E402
from ray.rllib.env.single_agent_episode import SingleAgentEpisode  # noqa: E402

import tamrm  # noqa: E402
import tamrm.rllib  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "rllib_ppo.py"

#: Per (env episode, agent): the agent steps the env made, in order, as the env saw them:
#: (action, reward since the agent's action, terminated, truncated).
LOG: dict[tuple[int, Any], list[tuple[Any, float, bool, bool]]] = defaultdict(list)
_EPISODES = itertools.count()
_INSTANCES = itertools.count()


def _reward(t: int, agent: Any, action: Any) -> float:
    """A deterministic reward the test can recompute: env step, agent and action."""
    a = float(np.sum(np.asarray(action, dtype=np.float64)))
    return ((t * 5 + len(str(agent)) * 3 + round(a * 7)) % 11) / 4.0


class RandomAgents(MultiAgentEnv):  # type: ignore[misc]
    """Agents that join late ("c"), die at random steps (terminated, "c" without a last
    observation), observe only every other step ("d": rewards pile up between its
    observations), and are truncated together at a random time limit."""

    SPACES: ClassVar[dict[str, int]] = {"a": 3, "b": 3, "c": 2, "d": 3}

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.rng = np.random.default_rng(int((config or {}).get("seed", 0)) + next(_INSTANCES))
        self.possible_agents = list(self.SPACES)
        self.agents: list[str] = []
        self.observation_spaces = {
            a: gym.spaces.Box(-100.0, 100.0, (2,), np.float32) for a in self.possible_agents
        }
        self.action_spaces = {a: gym.spaces.Discrete(n) for a, n in self.SPACES.items()}

    def _obs(self, agent: str) -> np.ndarray:
        return np.array([self.t, len(LOG[(self.ep, agent)])], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        self.ep = next(_EPISODES)
        self.t = 0
        self.limit = int(self.rng.integers(3, 14))
        self.join = {"a": 0, "b": 0, "c": int(self.rng.integers(0, 3)), "d": 0}
        # Nobody dies before "c" has joined: RLlib ends a multi-agent episode once every
        # agent it has seen is done.
        self.death = {a: int(self.rng.integers(3, self.limit + 3)) for a in self.SPACES}
        self.alive = set(self.SPACES)
        self.pending: dict[str, Any] = {}
        self.acc: dict[str, float] = {}
        self.agents = [a for a in self.SPACES if self.join[a] == 0]
        return {a: self._obs(a) for a in self.agents}, {a: {"ep": self.ep} for a in self.agents}

    def _observes(self, agent: str) -> bool:
        if agent == "d":
            return (self.t - self.join[agent]) % 2 == 0
        return self.t >= self.join[agent]

    def step(self, action_dict: dict[str, Any]) -> Any:
        self.t += 1
        for agent, action in action_dict.items():
            self.pending[agent] = action
            self.acc[agent] = 0.0
        now = {agent: _reward(self.t, agent, action) for agent, action in self.pending.items()}
        for agent, r in now.items():
            self.acc[agent] += r
        obs, rew, term, trunc, info = {}, {}, {}, {}, {}
        truncate_all = self.t >= self.limit
        for agent in sorted(self.alive):
            dies = self.death[agent] <= self.t and not truncate_all
            sees = self._observes(agent) or dies or truncate_all
            if self.t < self.join[agent]:
                continue
            if dies:
                self.alive.discard(agent)
                term[agent] = True
            if agent in self.pending:
                rew[agent] = now[agent]  # RLlib adds up an agent's rewards between its steps
            if dies and agent == "c" and agent in self.pending:
                sees = False  # terminated without a last observation
            if sees:
                obs[agent] = self._obs(agent)
                info[agent] = {"ep": self.ep}
            if agent in self.pending and (sees or dies):
                LOG[(self.ep, agent)].append(
                    (self.pending.pop(agent), self.acc.pop(agent), dies, truncate_all)
                )
            if truncate_all and agent in obs:
                trunc[agent] = True
        done_all = not self.alive
        term["__all__"] = done_all and not truncate_all
        trunc["__all__"] = truncate_all
        self.agents = sorted(self.alive)
        return obs, rew, term, trunc, info


class Countdown(gym.Env[np.ndarray, Any]):
    """A single-agent env: terminates or truncates at a random step; logs what it got."""

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        config = config or {}
        self.continuous = bool(config.get("continuous", False))
        self.rng = np.random.default_rng(int(config.get("seed", 0)) + next(_INSTANCES))
        self.observation_space = gym.spaces.Box(-100.0, 100.0, (2,), np.float32)
        if self.continuous:
            self.action_space: gym.Space[Any] = gym.spaces.Box(
                np.array([-2.0, 0.0], np.float32), np.array([2.0, 5.0], np.float32)
            )
        else:
            self.action_space = gym.spaces.Discrete(3)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        self.ep = next(_EPISODES)
        self.t = 0
        self.end = int(self.rng.integers(1, 12))
        self.truncates = bool(self.rng.integers(0, 2))
        return np.array([0.0, self.end], np.float32), {"ep": self.ep}

    def step(self, action: Any) -> Any:
        self.t += 1
        action = np.array(action, dtype=np.float32) if self.continuous else int(action)
        reward = _reward(self.t, DEFAULT_AGENT_ID, action)
        done = self.t >= self.end
        term, trunc = done and not self.truncates, done and self.truncates
        LOG[(self.ep, DEFAULT_AGENT_ID)].append((action, reward, term, trunc))
        obs = np.array([self.t, self.end], np.float32)
        return obs, reward, term, trunc, {"ep": self.ep}


ALPHA = 0.7


def _frozen_task(client: tamrm.Client, task_id: str, num_actions: int, seed: int) -> None:
    """A task whose pool is full of high-scoring trajectories: no env episode enters it,
    so every learner sees the same pool whatever the order of their steps."""
    client.create_task(
        task_id,
        num_actions=num_actions,
        pool_capacity=4,
        k=2,
        start_step=1,
        min_pool_size=4,
        alpha=ALPHA,
    )
    rng = np.random.default_rng(seed)
    for i in range(4):
        length = int(rng.integers(8, 20))
        client.add_trajectory(task_id, rng.integers(0, num_actions, length), 1000.0 + i)


def _agent_chunks(episodes: list[Any]) -> Iterator[tuple[int, Any, Any]]:
    """(env episode, agent id, SingleAgentEpisode chunk) of every chunk sampled."""
    for episode in episodes:
        if hasattr(episode, "agent_episodes"):
            for agent, sa in episode.agent_episodes.items():
                if len(sa):
                    yield int(sa.get_infos(0)["ep"]), agent, sa
        elif len(episode):
            yield int(episode.get_infos(0)["ep"]), DEFAULT_AGENT_ID, episode


def _expected_rewards(
    client: tamrm.Client, keys: set[tuple[int, Any]], task_of: Any, reference: dict[str, str]
) -> dict[tuple[int, Any], np.ndarray]:
    """Each agent episode replayed alone through a one-env session on a twin task."""
    sessions = {t: client.session(ref, 1) for t, ref in reference.items()}
    try:
        out = {}
        for key in sorted(keys, key=str):
            session = sessions[task_of(key[1])]
            shaped = []
            for action, reward, term, trunc in LOG[key]:
                shaped.append(session.step([action], [reward], [term], [trunc]).rewards[0])
            if session.episodes_in_progress[0]:
                session.abandon([0])
            out[key] = np.array(shaped)
        return out
    finally:
        for s in sessions.values():
            s.close()


def _check_chunks(episodes: list[Any], expected: dict[tuple[int, Any], np.ndarray]) -> int:
    """Every sampled agent step: the env's action and reward, shaped as ``expected``;
    returns the number of agent steps (some of which had the kNN term)."""
    steps = active = 0
    for ep, agent, sa in _agent_chunks(episodes):
        log = LOG[(ep, agent)]
        for k in range(len(sa)):
            n = sa.t_started + k
            action, reward, _, _ = log[n]
            info = sa.get_infos(k + 1)
            assert info["original_reward"] == reward, (ep, agent, n)
            assert info["shaping_step"] == n
            sent = np.asarray(sa.get_actions(k))
            if np.asarray(action).dtype.kind == "f":
                assert sent.shape == np.asarray(action).shape
            else:
                assert int(sent) == action
            assert sa.get_rewards(k) == expected[(ep, agent)][n], (ep, agent, n)
            assert sa.get_rewards(k) == pytest.approx(reward + ALPHA * info["knn_reward"])
            steps += 1
            active += info["knn_active"]
        if sa.is_done:
            # (RLlib also marks the truncated last steps terminated when every agent is
            # done; both are episode ends to tamrm.)
            assert (log[-1][2] or sa.is_truncated) and (log[-1][3] <= sa.is_truncated)
            assert len(log) == sa.t_started + len(sa)
    assert active > 0
    return steps


def _ma_config(task: Any, address: str, num_envs: int, **options: Any) -> PPOConfig:
    return (
        PPOConfig()
        .environment(RandomAgents)
        .multi_agent(
            # One module per action space.
            policies={"p2", "p3"},
            policy_mapping_fn=lambda aid, episode, **kw: f"p{RandomAgents.SPACES[aid]}",
        )
        .env_runners(
            num_env_runners=0,
            num_envs_per_env_runner=num_envs,
            env_to_module_connector=tamrm.rllib.knn_connector(task, address=address, **options),
        )
        .environment(disable_env_checking=True)
    )


def _piece(runner: Any) -> tamrm.rllib.KnnShaping:
    (piece,) = [
        p
        for p in tamrm.rllib._pieces(runner._env_to_module)
        if isinstance(p, tamrm.rllib.KnnShaping)
    ]
    return piece


@settings(max_examples=6)
@given(seed=st.integers(0, 2**16), num_envs=st.integers(1, 3), local=st.booleans())
def test_multi_agent_steps_shaped_as_one_env_sessions(
    server: tamrm.LocalServer, remote_client: tamrm.Client, seed: int, num_envs: int, local: bool
) -> None:
    base = f"ma/{seed}/{num_envs}/{local}/{next(_INSTANCES)}"
    # a and b share a pool, c (two actions) and d have their own.
    names = {"a": f"{base}/ab", "b": f"{base}/ab", "c": f"{base}/c", "d": f"{base}/d"}
    reference = {}
    for agent, task in names.items():
        if task not in reference:
            n = RandomAgents.SPACES[agent]
            _frozen_task(remote_client, task, n, seed + n)
            _frozen_task(remote_client, f"{task}/ref", n, seed + n)
            reference[task] = f"{task}/ref"
    runner = MultiAgentEnvRunner(
        config=_ma_config(names.__getitem__, server.address, num_envs, local=local).environment(
            env_config={"seed": seed}
        )
    )
    try:
        sampled = [runner.sample(num_timesteps=40) for _ in range(2)]
        counts = tamrm.rllib.close_sessions(runner)
    finally:
        runner.stop()
    episodes = [e for batch in sampled for e in batch]
    keys = {(ep, agent) for ep, agent, _ in _agent_chunks(episodes)}
    expected = _expected_rewards(remote_client, keys, names.__getitem__, reference)
    steps = _check_chunks(episodes, expected)
    # Every agent step RLlib recorded was shaped once, every agent episode RLlib ended was
    # ended once, and they reached their tasks' counters.
    recorded = _recorded(episodes)
    assert steps == sum(n for n, _ in recorded.values()) == counts.agent_steps
    assert counts.episodes == sum(done for _, done in recorded.values())
    for key, (n, done) in recorded.items():
        # The env's own episode: RLlib recorded all of it, or a prefix whose end it lost
        # (RLlib 2.60 drops the last step of an agent terminated without an observation
        # right after it cut the chunk), which was then abandoned.
        assert n == len(LOG[key]) or (n < len(LOG[key]) and not done and counts.abandoned)
    # Not vacuous: agents died before their episode's end, and "c" joined late.
    assert any(done and LOG[k][-1][2] for k, (_, done) in recorded.items())
    assert any(
        a == "c" and sa.t_started == 0 and sa.get_observations(0)[0] > 0
        for _, a, sa in _agent_chunks(episodes)
    )
    for task in set(names.values()):
        mine = [v for k, v in recorded.items() if names[k[1]] == task]
        stats = remote_client.get_task(task).stats
        assert stats.steps_shaped == sum(n for n, _ in mine)
        assert stats.episodes_completed == sum(done for _, done in mine)
        assert stats.pool_size == 4 and stats.best_score == 1003.0


def _recorded(episodes: list[Any]) -> dict[tuple[int, Any], tuple[int, bool]]:
    """Per (env episode, agent): the agent steps RLlib recorded, whether it ended them."""
    out: dict[tuple[int, Any], tuple[int, bool]] = {}
    for ep, agent, sa in _agent_chunks(episodes):
        n, done = out.get((ep, agent), (0, False))
        out[(ep, agent)] = (max(n, sa.t_started + len(sa)), done or sa.is_done)
    return out


@settings(max_examples=4)
@given(seed=st.integers(0, 2**16), num_envs=st.integers(1, 3))
def test_single_agent_steps_shaped_as_one_env_sessions(
    server: tamrm.LocalServer, remote_client: tamrm.Client, seed: int, num_envs: int
) -> None:
    task = f"sa/{seed}/{num_envs}/{next(_INSTANCES)}"
    _frozen_task(remote_client, task, 3, seed)
    _frozen_task(remote_client, f"{task}/ref", 3, seed)
    config = (
        PPOConfig()
        .environment(Countdown, env_config={"seed": seed})
        .env_runners(
            num_env_runners=0,
            num_envs_per_env_runner=num_envs,
            env_to_module_connector=tamrm.rllib.knn_connector(task, address=server.address),
        )
    )
    runner = SingleAgentEnvRunner(config=config)
    try:
        episodes = runner.sample(num_timesteps=30) + runner.sample(num_timesteps=30)
        counts = tamrm.rllib.close_sessions(runner)
    finally:
        runner.stop()
    keys = {(ep, agent) for ep, agent, _ in _agent_chunks(episodes)}
    expected = _expected_rewards(remote_client, keys, lambda _: task, {task: f"{task}/ref"})
    steps = _check_chunks(episodes, expected)
    assert steps == counts.agent_steps == remote_client.get_task(task).stats.steps_shaped


def test_continuous_actions_reach_the_pool_as_the_env_got_them(
    server: tamrm.LocalServer, remote_client: tamrm.Client, task_id: str
) -> None:
    remote_client.create_task(task_id, action_dim=2, pool_capacity=200, min_pool_size=1)
    config = (
        PPOConfig()
        .environment(Countdown, env_config={"continuous": True, "seed": 3})
        .env_runners(
            num_env_runners=0,
            num_envs_per_env_runner=2,
            env_to_module_connector=tamrm.rllib.knn_connector(task_id, address=server.address),
        )
    )
    runner = SingleAgentEnvRunner(config=config)
    try:
        episodes = runner.sample(num_episodes=6)
        tamrm.rllib.close_sessions(runner)
    finally:
        runner.stop()
    eps = {int(e.get_infos(0)["ep"]) for e in episodes}
    got = sorted(t.actions.tobytes() for t in remote_client.get_pool(task_id).trajectories)
    want = sorted(
        np.array([a for a, *_ in LOG[(ep, DEFAULT_AGENT_ID)]], dtype=np.float32).tobytes()
        for ep in eps
    )
    assert got == want
    # The module's actions (in [-1, 1] before RLlib's unsquashing) are not what was sent.
    module_actions = np.concatenate([np.asarray(e.get_actions()) for e in episodes])
    env_actions = np.concatenate(
        [np.array([a for a, *_ in LOG[(ep, DEFAULT_AGENT_ID)]]) for ep in eps]
    )
    assert not np.allclose(np.sort(module_actions, axis=0), np.sort(env_actions, axis=0))


def test_a_reset_abandons_the_episodes_in_progress(
    server: tamrm.LocalServer, remote_client: tamrm.Client
) -> None:
    base = f"reset/{next(_INSTANCES)}"
    names = {a: f"{base}/{RandomAgents.SPACES[a]}" for a in RandomAgents.SPACES}
    for n in {2, 3}:
        remote_client.create_task(f"{base}/{n}", num_actions=n)
    runner = MultiAgentEnvRunner(config=_ma_config(names.__getitem__, server.address, 3))
    try:
        runner.sample(num_timesteps=20)
        piece = _piece(runner)
        in_progress = sum(int(s.episodes_in_progress.sum()) for s in piece.sessions.values())
        assert in_progress > 0
        before = piece.counts()
        # sample(num_episodes=...) resets every sub-environment first.
        episodes = runner.sample(num_episodes=3)
        after = piece.counts()
        assert after.abandoned - before.abandoned == in_progress
        for _, _, sa in _agent_chunks(episodes):
            if sa.t_started == 0:
                assert sa.get_infos(1)["shaping_step"] == 0
        tamrm.rllib.close_sessions(runner)
    finally:
        runner.stop()
    ended = sum(remote_client.get_task(t).stats.episodes_completed for t in set(names.values()))
    assert ended == after.episodes  # the abandoned ones never counted


def test_shared_task_needs_matching_action_spaces(
    server: tamrm.LocalServer, remote_client: tamrm.Client, task_id: str
) -> None:
    remote_client.create_task(task_id, num_actions=3)
    runner = MultiAgentEnvRunner(config=_ma_config(task_id, server.address, 1))
    try:
        with pytest.raises(ValueError, match=r"agent 'c', task '.*': task has num_actions=3"):
            for _ in range(10):
                runner.sample(num_timesteps=10)
    finally:
        runner.stop()


def test_missing_task_is_named(server: tamrm.LocalServer, task_id: str) -> None:
    config = (
        PPOConfig()
        .environment(Countdown)
        .env_runners(
            num_env_runners=0,
            env_to_module_connector=tamrm.rllib.knn_connector(task_id, address=server.address),
        )
    )
    runner = SingleAgentEnvRunner(config=config)
    try:
        with pytest.raises(tamrm.TaskNotFound, match=f"task '{task_id}'.*create the task"):
            runner.sample(num_timesteps=4)
    finally:
        runner.stop()


def test_bad_options_fail_on_the_driver() -> None:
    with pytest.raises(TypeError, match="task must be a task id"):
        tamrm.rllib.knn_connector(3)
    with pytest.raises(TypeError, match="local must be a bool"):
        tamrm.rllib.knn_connector("t", local="yes")
    with pytest.raises(TypeError, match="unexpected keyword"):
        tamrm.rllib.knn_connector("t", adress="x:1")
    with pytest.raises(TypeError, match="needs beta"):
        tamrm.rllib.potential_connector(gamma=0.9)
    with pytest.raises(ValueError, match=r"gamma must be in \[0, 1\]"):
        tamrm.rllib.potential_connector(beta=1.0, gamma=1.5)
    piece = tamrm.rllib.KnnShaping(task=lambda agent: 7)
    with pytest.raises(TypeError, match="returned 7 for agent 'x'"):
        tamrm.rllib._task_of(piece.task, "x")


def test_one_client_per_process(monkeypatch: pytest.MonkeyPatch, server: tamrm.LocalServer) -> None:
    monkeypatch.setenv("TAMRM_ADDRESS", server.address)
    monkeypatch.delenv("TAMRM_API_KEY", raising=False)
    first = tamrm.rllib.process_client()
    assert tamrm.rllib.process_client(server.address) is first
    assert tamrm.rllib.process_client(server.address, timeout=5.0) is not first
    assert first.target == server.address
    # The key, too, is the EnvRunner process's own TAMRM_API_KEY when not given.
    monkeypatch.setenv("TAMRM_API_KEY", "runner-key")
    keyed = tamrm.rllib.process_client()
    assert keyed is not first and keyed._connection["api_key"] == "runner-key"
    assert tamrm.rllib.process_client(api_key="runner-key") is keyed


def test_pickled_connector_and_config_shape_on_their_own(
    server: tamrm.LocalServer, remote_client: tamrm.Client, task_id: str
) -> None:
    remote_client.create_task(task_id, num_actions=3)
    config = _ma_config(lambda agent: task_id if agent != "c" else task_id + "c", server.address, 2)
    remote_client.create_task(task_id + "c", num_actions=2)
    runner = MultiAgentEnvRunner(config=config)
    try:
        runner.sample(num_timesteps=10)
        piece = _piece(runner)
        assert piece.sessions  # open
        copy = pickle.loads(cloudpickle.dumps(piece))
        assert not copy.sessions and copy.counts() == tamrm.rllib.ShapingCounts()
        # A whole config (RLlib cloudpickles it to every EnvRunner) builds a working runner.
        twin = MultiAgentEnvRunner(config=pickle.loads(cloudpickle.dumps(config)))
        try:
            twin.sample(num_timesteps=10)
            assert _piece(twin).counts().agent_steps > 0
            assert not set(_piece(twin).sessions.values()) & set(piece.sessions.values())
            tamrm.rllib.close_sessions(twin)
        finally:
            twin.stop()
        assert not piece.sessions[task_id].closed
        tamrm.rllib.close_sessions(runner)
    finally:
        runner.stop()


# -- the learner piece --------------------------------------------------------------------

OBS = gym.spaces.Box(-5.0, 5.0, (3,), np.float32)


@pytest.fixture(scope="module")
def module() -> Any:
    spec = PPOConfig().get_default_rl_module_spec()
    spec.observation_space, spec.action_space = OBS, gym.spaces.Discrete(2)
    torch.manual_seed(0)
    return MultiRLModuleSpec(rl_module_specs={DEFAULT_MODULE_ID: spec}).build()


def _naive_values(module: Any, obs: np.ndarray) -> np.ndarray:
    """V of each observation on its own (one forward pass per observation)."""
    sub = module[DEFAULT_MODULE_ID]
    with torch.no_grad():
        return np.array(
            [float(sub.compute_values({Columns.OBS: torch.tensor(o[None])})[0]) for o in obs]
        )


def _episode(rng: np.random.Generator, length: int, end: str, t_started: int) -> SingleAgentEpisode:
    return SingleAgentEpisode(
        observations=list(rng.uniform(-5, 5, (length + 1, 3)).astype(np.float32)),
        actions=list(rng.integers(0, 2, length)),
        rewards=list(rng.uniform(-1, 1, length)),
        terminated=end == "terminated",
        truncated=end == "truncated",
        t_started=t_started,
        len_lookback_buffer=0,
        observation_space=OBS,
        action_space=gym.spaces.Discrete(2),
    ).to_numpy()


def _expected(
    module: Any, sa: SingleAgentEpisode, rewards: np.ndarray, beta: float, gamma: float, n: int
) -> np.ndarray:
    v = _naive_values(module, np.asarray(sa.get_observations(slice(0, n + 1))))
    if sa.is_terminated:
        v[n] = 0.0
    return rewards + beta * (gamma * v[1:] - v[:-1])


@settings(max_examples=15)
@given(
    seed=st.integers(0, 2**16),
    chunks=st.lists(
        st.tuples(
            st.integers(1, 6),
            st.sampled_from(["terminated", "truncated", "cut"]),
            st.integers(0, 50),
        ),
        min_size=1,
        max_size=4,
    ),
    ppo_bootstrap=st.booleans(),
    beta=st.floats(0.1, 2.0),
    gamma=st.floats(0.0, 1.0),
)
def test_potential_added_once(
    module: Any,
    seed: int,
    chunks: list[tuple[int, str, int]],
    ppo_bootstrap: bool,
    beta: float,
    gamma: float,
) -> None:
    rng = np.random.default_rng(seed)
    episodes = [_episode(rng, n, end, t0) for n, end, t0 in chunks]
    originals = [np.asarray(e.get_rewards(), dtype=np.float64).copy() for e in episodes]
    piece = tamrm.rllib.potential_connector(beta=beta, gamma=gamma)(None, None)
    shared: dict[str, Any] = {}
    if ppo_bootstrap:  # PPO's learner pipeline: one artificial step appended first
        AddOneTsToEpisodesAndTruncate()(
            rl_module=module, batch={}, episodes=episodes, shared_data=shared
        )
    piece(rl_module=module, batch={}, episodes=episodes, shared_data=shared)
    once = [np.asarray(e.get_rewards(), dtype=np.float64).copy() for e in episodes]
    for sa, original, got, (n, _, _) in zip(episodes, originals, once, chunks, strict=True):
        np.testing.assert_allclose(
            got[:n], _expected(module, sa, original, beta, gamma, n), rtol=1e-5, atol=1e-5
        )
        if ppo_bootstrap:
            assert got[n] == 0.0  # the artificial step is left alone
    # The same episodes again, a second piece, a pickle round trip: nothing more is added.
    piece(rl_module=module, batch={}, episodes=episodes, shared_data=shared)
    tamrm.rllib.potential_connector(beta=beta, gamma=gamma)(None, None)(
        rl_module=module, batch={}, episodes=episodes, shared_data=shared
    )
    copies = pickle.loads(pickle.dumps(episodes))
    piece(rl_module=module, batch={}, episodes=copies, shared_data=shared)
    for e, c, want in zip(episodes, copies, once, strict=True):
        np.testing.assert_array_equal(np.asarray(e.get_rewards()), want)
        np.testing.assert_array_equal(np.asarray(c.get_rewards()), want)


def test_replayed_slices_leave_the_stored_episode_alone(module: Any) -> None:
    rng = np.random.default_rng(1)
    stored = _episode(rng, 12, "terminated", 0)
    raw = np.asarray(stored.get_rewards(), dtype=np.float64).copy()
    piece = tamrm.rllib.PotentialShaping(beta=1.0, gamma=0.9)
    # Two samples of the same stored steps (a replay buffer's slices share its arrays).
    for _ in range(2):
        sample = stored.slice(slice(3, 9))
        piece(rl_module=module, batch={}, episodes=[sample], shared_data={})
        np.testing.assert_array_equal(np.asarray(stored.get_rewards()), raw)
        want = _expected(module, sample, raw[3:9], 1.0, 0.9, 6)
        np.testing.assert_allclose(np.asarray(sample.get_rewards()), want, rtol=1e-5, atol=1e-5)
    # A chunk overlapping a shaped one but not equal to it is refused, not shaped twice.
    sample = stored.slice(slice(3, 9))
    piece(rl_module=module, batch={}, episodes=[sample], shared_data={})
    sample.custom_data[tamrm.rllib.POTENTIAL_MARK] = (4, 7)
    with pytest.raises(RuntimeError, match="refusing to add F twice"):
        piece(rl_module=module, batch={}, episodes=[sample], shared_data={})


def test_gate_potential_reads_knn_active(module: Any) -> None:
    rng = np.random.default_rng(2)
    sa = _episode(rng, 5, "truncated", 0)
    active = [True, False, True, True, False]
    for k, flag in enumerate(active):
        sa.infos.set(new_data={"knn_active": flag}, at_indices=k + 1)
    raw = np.asarray(sa.get_rewards(), dtype=np.float64).copy()
    tamrm.rllib.PotentialShaping(beta=1.0, gamma=0.9, gate_potential=True)(
        rl_module=module, batch={}, episodes=[sa], shared_data={}
    )
    full = _expected(module, sa, raw, 1.0, 0.9, 5)
    want = np.where(active, full, raw)
    np.testing.assert_allclose(np.asarray(sa.get_rewards()), want, rtol=1e-5, atol=1e-5)
    bare = _episode(rng, 3, "cut", 0)
    with pytest.raises(ValueError, match="no 'knn_active' info"):
        tamrm.rllib.PotentialShaping(beta=1.0, gamma=0.9, gate_potential=True)(
            rl_module=module, batch={}, episodes=[bare], shared_data={}
        )


def test_learner_piece_errors(module: Any) -> None:
    rng = np.random.default_rng(3)
    piece = tamrm.rllib.PotentialShaping(beta=1.0, gamma=0.9)
    with pytest.raises(RuntimeError, match="before RLlib's default learner pieces"):
        piece(
            rl_module=module,
            batch={DEFAULT_MODULE_ID: {Columns.REWARDS: np.zeros(3)}},
            episodes=[_episode(rng, 3, "cut", 0)],
            shared_data={},
        )
    other = SingleAgentEpisode(
        observations=[np.zeros(3, np.float32)] * 3,
        actions=[0, 1],
        rewards=[1.0, 1.0],
        module_id="critic-less",
        len_lookback_buffer=0,
    ).to_numpy()

    class NoCritic:
        def is_stateful(self) -> bool:
            return False

    with pytest.raises(TypeError, match=r"module 'critic-less' .* no value function"):
        piece(rl_module=NoCritic(), batch={}, episodes=[other], shared_data={})
    # Left out by modules=..., it is not touched.
    tamrm.rllib.PotentialShaping(beta=1.0, gamma=0.9, modules={DEFAULT_MODULE_ID})(
        rl_module=NoCritic(), batch={}, episodes=[other], shared_data={}
    )
    assert list(other.get_rewards()) == [1.0, 1.0]


# -- real PPO runs ------------------------------------------------------------------------


def _run(args: list[str], server_binary: str) -> str:
    proc = subprocess.run(
        [sys.executable, *args],
        capture_output=True,
        text=True,
        env=dict(os.environ, TAMRM_BIN=server_binary),
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def test_rllib_ppo_example_quick(server: tamrm.LocalServer, server_binary: str) -> None:
    # Two EnvRunner actors and a learner on one server; the example checks the server's
    # counters against what RLlib sampled. (Run before this module starts its own Ray.)
    out = _run(
        [str(EXAMPLE), "--quick", "--server", server.address, "--tasks", "shared"], server_binary
    )
    assert out.count("iteration ") == 2, out
    assert re.search(r"EnvRunner 1: [1-9]\d* agent steps", out), out
    assert re.search(r"EnvRunner 2: [1-9]\d* agent steps", out), out
    assert "every agent step and agent episode reached the server once" in out, out


def test_guide_snippet_runs_alone(server_binary: str, tmp_path: Path) -> None:
    text = (REPO_ROOT / "docs" / "multi-agent.md").read_text()
    section = text[text.index("## Ray RLlib\n") :]
    (code,) = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    script = tmp_path / "snippet.py"
    script.write_text(code)
    out = _run([str(script)], server_binary)
    assert "knn_reward_mean" in out and "env_episode_return_mean" in out, out
    steps = re.search(r"steps_shaped=(\d+)", out)
    assert steps and int(steps.group(1)) > 0, out


class Probe(ConnectorV2):  # type: ignore[misc]
    """After PotentialShaping: records each chunk's rewards and V computed beside it."""

    calls: ClassVar[list[list[tuple[Any, ...]]]] = []

    def __call__(self, *, rl_module: Any, batch: Any, episodes: Any, **kwargs: Any) -> Any:
        rows = []
        for sa in episodes:
            n = len(sa) - 1  # PPO's artificial last step
            obs = np.asarray(sa.get_observations(slice(0, n + 1)))
            rows.append(
                (
                    np.asarray(sa.get_rewards(slice(0, n)), dtype=np.float64).copy(),
                    _naive_values(rl_module, obs),
                    obs,
                    bool(sa.is_terminated),
                    list(sa.get_infos(slice(1, n + 1))),
                )
            )
        Probe.calls.append(rows)
        return batch


@pytest.fixture(scope="module")
def ray_session() -> Iterator[None]:
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()


def test_ppo_adds_the_potential_once_per_update(
    ray_session: None, server: tamrm.LocalServer, remote_client: tamrm.Client, task_id: str
) -> None:
    task = remote_client.create_task(
        task_id, num_actions=2, pool_capacity=5, start_step=0, min_pool_size=1, beta=0.5, gamma=0.9
    )
    Probe.calls.clear()
    config = (
        PPOConfig()
        .environment("CartPole-v1")
        .env_runners(
            num_env_runners=0,
            num_envs_per_env_runner=2,
            rollout_fragment_length=32,
            env_to_module_connector=tamrm.rllib.knn_connector(task_id, address=server.address),
        )
        .learners(
            learner_connector=lambda obs, act: [
                tamrm.rllib.potential_connector(task)(obs, act),
                Probe(),
            ],
        )
        .training(train_batch_size_per_learner=64, minibatch_size=16, num_epochs=3)
    )
    algo = config.build_algo()
    try:
        for _ in range(2):
            algo.train()
        tamrm.rllib.close_sessions(algo.env_runner)
    finally:
        algo.stop()
    assert len(Probe.calls) == 2  # one learner-pipeline pass per update, whatever the epochs
    steps = 0
    for rows in Probe.calls:
        for rewards, v, _, terminated, infos in rows:
            if terminated:
                v[-1] = 0.0
            knn = np.array(
                [i["original_reward"] + task.config.alpha * i["knn_reward"] for i in infos]
            )
            np.testing.assert_allclose(
                rewards, knn + 0.5 * (0.9 * v[1:] - v[:-1]), rtol=1e-5, atol=1e-5
            )
            steps += len(rewards)
    assert steps == remote_client.get_task(task_id).stats.steps_shaped
