"""Episode scores from ``info`` (``score_key``) through every wrapper, against the real
server: the pool must hold the env's score for episodes that report one, and the sum of
the environment rewards (SPEC §6 default) for those that do not (time-limit truncations).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.wrappers import TimeLimit

import tamrm
import tamrm.gym

LIMIT = 8  # TimeLimit: episodes longer than this are truncated and report no score


class ScoredCorridor(gym.Env[np.ndarray, int]):
    """Reward 1 per step; ends (terminated) after a random 2..11 steps with
    ``info["score"] = 100 / steps`` on that step, like the maze's success score."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(0.0, 20.0, (1,), np.float32)
        self.action_space = spaces.Discrete(2)
        self._length = 0
        self._t = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._length = int(self.np_random.integers(2, 12))
        self._t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._t += 1
        terminated = self._t >= self._length
        info: dict[str, Any] = {"score": 100.0 / self._t} if terminated else {}
        return np.array([self._t], np.float32), 1.0, terminated, False, info


def make_env() -> gym.Env[np.ndarray, int]:
    return TimeLimit(ScoredCorridor(), max_episode_steps=LIMIT)


def expected_score(steps: int, terminated: bool) -> float:
    return 100.0 / steps if terminated else float(steps)  # truncated: sum of rewards


def create(client: tamrm.Client, task_id: str) -> None:
    # A pool big enough to keep every episode, so it lists them all in completion order.
    client.create_task(task_id, num_actions=2, pool_capacity=1000, start_step=1)


def check_pool(client: tamrm.Client, task_id: str, episodes: list[tuple[int, float]]) -> None:
    pool = client.get_pool(task_id)
    got = [(len(t.actions), t.score) for t in pool.trajectories]
    assert len(got) == len(episodes)
    for (length, score), (want_length, want_score) in zip(got, episodes, strict=True):
        assert length == want_length
        assert score == pytest.approx(want_score, rel=1e-12)
    # Both kinds occurred, so both paths were exercised.
    assert any(length < LIMIT for length, _ in episodes)
    assert any(length == LIMIT for length, _ in episodes)


def test_shaped_reward_score_key(client: tamrm.Client, task_id: str) -> None:
    create(client, task_id)
    episodes: list[tuple[int, float]] = []
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(make_env(), session, score_key="score")
        env.reset(seed=1)
        steps = 0
        while len(episodes) < 30:
            _, _, terminated, truncated, _ = env.step(int(env.action_space.sample()))
            steps += 1
            if terminated or truncated:
                episodes.append((steps, expected_score(steps, terminated)))
                steps = 0
                env.reset()
    check_pool(client, task_id, episodes)


def test_shaped_reward_without_score_key_sums_rewards(client: tamrm.Client, task_id: str) -> None:
    create(client, task_id)
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(make_env(), session)
        env.reset(seed=2)
        steps = 0
        done = False
        while not done:
            _, _, terminated, truncated, info = env.step(0)
            steps += 1
            done = terminated or truncated
        assert "score" in info or truncated
    (traj,) = client.get_pool(task_id).trajectories
    assert traj.score == float(steps)


@pytest.mark.parametrize(
    "mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED]
)
def test_vector_score_key(client: tamrm.Client, task_id: str, mode: AutoresetMode) -> None:
    n = 3
    create(client, task_id)
    envs = SyncVectorEnv([make_env for _ in range(n)], autoreset_mode=mode)
    episodes: list[tuple[int, float]] = []
    steps = np.zeros(n, dtype=np.int64)
    pending_reset = np.zeros(n, dtype=np.bool_)
    with client.session(task_id, n) as session:
        env = tamrm.gym.VectorShapedReward(envs, session, score_key="score")
        env.reset(seed=5)
        while len(episodes) < 40:
            if mode == AutoresetMode.DISABLED and pending_reset.any():
                env.reset(options={"reset_mask": pending_reset})
                pending_reset[:] = False
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            # NEXT_STEP: a sub-env whose episode ended last step only resets on this one.
            active = ~pending_reset if mode == AutoresetMode.NEXT_STEP else np.ones(n, bool)
            steps[active] += 1
            ended = (terminated | truncated) & active
            for i in np.flatnonzero(ended):  # rows are processed in order
                episodes.append((int(steps[i]), expected_score(int(steps[i]), bool(terminated[i]))))
                steps[i] = 0
            pending_reset = ended if mode != AutoresetMode.SAME_STEP else np.zeros(n, bool)
        env.close()
    check_pool(client, task_id, episodes)


def test_sb3_score_key(client: tamrm.Client, task_id: str) -> None:
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import DummyVecEnv

    import tamrm.sb3

    n = 3
    create(client, task_id)
    venv = DummyVecEnv([make_env for _ in range(n)])
    venv.seed(7)
    episodes: list[tuple[int, float]] = []
    steps = np.zeros(n, dtype=np.int64)
    with client.session(task_id, n) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session, score_key="score")
        env.reset()
        rng = np.random.default_rng(7)
        while len(episodes) < 40:
            _, _, dones, infos = env.step(rng.integers(0, 2, size=n))
            steps += 1
            for i in np.flatnonzero(dones):
                terminated = not infos[i].get("TimeLimit.truncated", False)
                episodes.append((int(steps[i]), expected_score(int(steps[i]), terminated)))
                steps[i] = 0
        env.close()
    check_pool(client, task_id, episodes)
