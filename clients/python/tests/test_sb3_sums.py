"""ShapedVecEnv's running sums: each episode's ``shaped_episode`` and ``take_stats``."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
from stable_baselines3.common.vec_env import DummyVecEnv

import tamrm.sb3

ALPHA, BETA = 0.7, 0.3
SHAPING = dict(num_actions=2, alpha=ALPHA, beta=BETA, gamma=0.9, k=2, start_step=2, min_pool_size=2)


def _value(obs: Any) -> np.ndarray:
    return np.asarray(obs, dtype=np.float64) @ np.array([0.3, -0.1, 2.0, 0.05])


def test_episode_sums_and_stats_equal_the_steps(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    n = 3
    venv = DummyVecEnv([lambda: gym.make("CartPole-v1", max_episode_steps=30)] * n)
    venv.seed(5)
    rng = np.random.default_rng(1)
    with client.session(task_id, n) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session, value_fn=_value)
        env.reset()
        # Per env, the steps of its current episode: (R_meta, R, r, F, knn_active).
        running: list[list[tuple[float, float, float, float, bool]]] = [[] for _ in range(n)]
        taken: list[tuple[float, float, float, float, bool]] = []  # since the last take_stats
        episodes = 0
        for t in range(400):
            if t in (150, 275):
                # Mid-episode resets: those episodes are abandoned, never reported, but
                # their steps stay in the stats.
                stats = env.take_stats()
                _check_stats(stats, taken, session.pool_version)
                taken = []
                env.reset()
                running = [[] for _ in range(n)]
            _, shaped, dones, infos = env.step(rng.integers(0, 2, size=n))
            for i, info in enumerate(infos):
                step = (
                    float(shaped[i]),
                    info["original_reward"],
                    info["knn_reward"],
                    info["potential"],
                    info["knn_active"],
                )
                np.testing.assert_allclose(
                    step[0], step[1] + ALPHA * step[2] + BETA * step[3], rtol=1e-6
                )
                running[i].append(step)
                taken.append(step)
                if dones[i]:
                    steps = np.array(running[i], dtype=np.float64)
                    parts = info["shaped_episode"]
                    assert parts["l"] == len(steps)
                    # R_meta is returned as float32 to SB3; the sums are of the float64 answers.
                    assert parts["r"] == pytest.approx(steps[:, 0].sum(), rel=1e-6)
                    assert parts["knn"] == pytest.approx(ALPHA * steps[:, 2].sum(), rel=1e-12)
                    assert parts["potential"] == pytest.approx(
                        BETA * steps[:, 3].sum(), rel=1e-12, abs=1e-12
                    )
                    running[i] = []
                    episodes += 1
                else:
                    assert "shaped_episode" not in info
            if t % 37 == 0:
                _check_stats(env.take_stats(), taken, session.pool_version)
                taken = []
        _check_stats(env.take_stats(), taken, session.pool_version)
        assert env.take_stats() == tamrm.sb3.ShapingStats()  # nothing since
        env.close()
    assert episodes > 30


def _check_stats(
    stats: tamrm.sb3.ShapingStats,
    steps: list[tuple[float, float, float, float, bool]],
    pool_version: int,
) -> None:
    if not steps:
        assert stats == tamrm.sb3.ShapingStats()
        return
    arr = np.array(steps, dtype=np.float64)
    assert stats.env_steps == len(steps)
    assert stats.reward_env == pytest.approx(arr[:, 1].sum(), rel=1e-12)
    assert stats.knn_term == pytest.approx(ALPHA * arr[:, 2].sum(), rel=1e-9, abs=1e-12)
    assert stats.potential_term == pytest.approx(BETA * arr[:, 3].sum(), rel=1e-9, abs=1e-12)
    assert stats.knn_active == int(arr[:, 4].sum())
    assert stats.pool_version == pool_version


def test_recording_refuses_mismatched_columns_and_changes_nothing(
    client: tamrm.Client, task_id: str
) -> None:
    from tamrm import _native

    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    venv = DummyVecEnv([lambda: gym.make("CartPole-v1")] * 2)
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        env.reset()
        _, _, dones, infos = env.step(np.zeros(2, dtype=np.int64))
        result = session.step(np.zeros(2, dtype=np.int64), np.ones(2))
        acc, steps = env._acc.copy(), env._env_steps
        rewards = np.ones(2)
        with pytest.raises(ValueError, match="num_envs = 2"):
            _native.record_step(env, infos, dones, np.ones(3), result, ALPHA, BETA)
        with pytest.raises(TypeError, match="2 dicts"):
            _native.record_step(env, infos[:1], dones, rewards, result, ALPHA, BETA)
        assert env._acc.tobytes() == acc.tobytes() and env._env_steps == steps
        _native.record_step(env, infos, dones, rewards, result, ALPHA, BETA)
        assert env._env_steps == steps + 2
        np.testing.assert_array_equal(env._acc[4], acc[4] + 1.0)
        env.close()
