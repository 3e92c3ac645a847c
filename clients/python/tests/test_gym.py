"""The gymnasium wrappers on real CartPole-v1 episodes, against the real server."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from reference import RefConfig, RefPool, RefStream

import tamrm
import tamrm.gym

W = np.array([0.3, -0.2, 1.5, 0.7])


def linear_value(obs: np.ndarray) -> np.ndarray:
    """A stand-in critic: V(s) = w . s."""
    return np.asarray(obs, dtype=np.float64) @ W


def v32(obs: np.ndarray) -> float:
    """The value as the server sees it (sent as a 32-bit float)."""
    return float(np.float32(linear_value(obs)))


def make_task(client: tamrm.Client, task_id: str) -> RefConfig:
    task = client.create_task(
        task_id,
        num_actions=2,
        pool_capacity=200,
        k=3,
        start_step=3,
        min_pool_size=3,
        gamma=0.97,
        alpha=0.6,
        beta=0.4,
    )
    return RefConfig.of(task.config)


def test_shaped_reward_cartpole(client: tamrm.Client, task_id: str) -> None:
    cfg = make_task(client, task_id)
    ref = RefPool(cfg)
    stream = RefStream(ref, 1)
    episodes: list[tuple[list[int], float]] = []
    ends = {"terminated": 0, "truncated": 0}
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(
            gym.make("CartPole-v1", max_episode_steps=25), session, value_fn=linear_value
        )
        env.action_space.seed(1)
        for episode in range(24):
            obs, _ = env.reset(seed=100 + episode)
            actions: list[int] = []
            total = 0.0
            done = False
            while not done:
                action = int(env.action_space.sample())
                next_obs, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                assert info["original_reward"] == 1.0
                assert info["shaping_step"] == len(actions)
                actions.append(action)
                total += info["original_reward"]
                want = stream.shape(0, action, 1.0, terminated, truncated, v32(obs), v32(next_obs))
                # F from the values sent: V(s') = 0 on termination, the real s' on truncation.
                v_next = 0.0 if terminated else v32(next_obs)
                assert info["potential"] == pytest.approx(cfg.gamma * v_next - v32(obs))
                assert reward == pytest.approx(
                    1.0 + cfg.alpha * info["knn_reward"] + cfg.beta * info["potential"],
                    rel=1e-12,
                )
                assert info["knn_active"] == want["knn_active"]
                assert info["knn_reward"] == pytest.approx(want["knn_reward"], abs=1e-12)
                assert reward == pytest.approx(want["reward"], rel=1e-6)
                assert info["pool_version"] == ref.version  # after the batch
                obs = next_obs
            ends["terminated" if terminated else "truncated"] += 1
            episodes.append((actions, total))
        env.close()
    assert ends["terminated"] > 0 and ends["truncated"] > 0
    pool = client.get_pool(task_id)
    assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == episodes
    assert client.get_task(task_id).stats.steps_shaped == sum(len(a) for a, _ in episodes)


def test_shaped_reward_reset_mid_episode(client: tamrm.Client, task_id: str) -> None:
    make_task(client, task_id)
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session)
        env.reset(seed=0)
        for _ in range(3):
            env.step(0)
        env.reset(seed=1)  # abandons the episode: the server must not continue it
        _, _, terminated, truncated, info = env.step(1)
        assert info["shaping_step"] == 0
        done = terminated or truncated
        steps = 1
        while not done:
            _, _, terminated, truncated, info = env.step(1)
            done = terminated or truncated
            steps += 1
    (traj,) = client.get_pool(task_id).trajectories
    assert traj.actions.tolist() == [1] * steps


def test_shaped_reward_checks_action_space(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=3)
    with client.session(task_id) as session, pytest.raises(ValueError, match="num_actions"):
        tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session)


def _vector_env(mode: AutoresetMode, n: int) -> SyncVectorEnv:
    return SyncVectorEnv(
        [lambda: gym.make("CartPole-v1", max_episode_steps=20) for _ in range(n)],
        autoreset_mode=mode,
    )


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_vector_shaped_reward_cartpole(
    client: tamrm.Client, task_id: str, mode: AutoresetMode
) -> None:
    n = 3
    cfg = make_task(client, task_id)
    ref = RefPool(cfg)
    stream = RefStream(ref, n)
    rng = np.random.default_rng(5)
    ended: list[tuple[list[int], float]] = []
    current: list[list[int]] = [[] for _ in range(n)]
    real_steps = 0
    kinds = {"terminated": 0, "truncated": 0, "skipped": 0}
    with client.session(task_id, n) as session:
        envs = tamrm.gym.VectorShapedReward(_vector_env(mode, n), session, value_fn=linear_value)
        assert envs.autoreset_mode == mode
        obs, _ = envs.reset(seed=11)
        pending_reset = np.zeros(n, dtype=bool)
        for _ in range(120):
            actions = rng.integers(0, 2, size=n)
            next_obs, rewards, terminated, truncated, info = envs.step(actions)
            for i in range(n):
                if mode == AutoresetMode.NEXT_STEP and pending_reset[i]:
                    # The autoreset step is not an environment step: not sent, not shaped.
                    kinds["skipped"] += 1
                    assert not info["_potential"][i] and not info["_knn_reward"][i]
                    assert rewards[i] == info["original_reward"][i] == 0.0
                    continue
                real_steps += 1
                done = bool(terminated[i] or truncated[i])
                if mode == AutoresetMode.SAME_STEP and done:
                    real_next = info["final_obs"][i]
                else:
                    real_next = next_obs[i]
                want = stream.shape(
                    i,
                    int(actions[i]),
                    float(info["original_reward"][i]),
                    bool(terminated[i]),
                    bool(truncated[i]),
                    v32(obs[i]),
                    v32(real_next),
                )
                assert info["_potential"][i]
                v_next = 0.0 if terminated[i] else v32(real_next)
                assert info["potential"][i] == pytest.approx(cfg.gamma * v_next - v32(obs[i]))
                assert info["shaping_step"][i] == want["step"] == len(current[i])
                assert info["knn_active"][i] == want["knn_active"]
                assert info["knn_reward"][i] == pytest.approx(want["knn_reward"], abs=1e-12)
                assert rewards[i] == pytest.approx(
                    info["original_reward"][i]
                    + cfg.alpha * info["knn_reward"][i]
                    + cfg.beta * info["potential"][i],
                    rel=1e-12,
                )
                assert rewards[i] == pytest.approx(want["reward"], rel=1e-6)
                current[i].append(int(actions[i]))
                if done:
                    kinds["terminated" if terminated[i] else "truncated"] += 1
                    ended.append((current[i], float(len(current[i]))))
                    current[i] = []
            pending_reset = terminated | truncated
            obs = next_obs
        envs.close()
    assert kinds["terminated"] > 2 and kinds["truncated"] > 2
    if mode == AutoresetMode.NEXT_STEP:
        assert kinds["skipped"] == kinds["terminated"] + kinds["truncated"] - int(
            pending_reset.sum()
        )
    else:
        assert kinds["skipped"] == 0
    stats = client.get_task(task_id).stats
    assert stats.steps_shaped == real_steps
    pool = client.get_pool(task_id)
    assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == ended
    assert pool.pool_version == ref.version


def test_vector_reset_mid_episode_restarts_stream(client: tamrm.Client, task_id: str) -> None:
    make_task(client, task_id)
    with client.session(task_id, 2) as session:
        envs = tamrm.gym.VectorShapedReward(_vector_env(AutoresetMode.NEXT_STEP, 2), session)
        envs.reset(seed=0)
        envs.step(np.array([0, 1]))
        envs.step(np.array([0, 1]))
        envs.reset(seed=1)
        _, _, _, _, info = envs.step(np.array([1, 1]))
        assert info["shaping_step"].tolist() == [0, 0]
        envs.close()
    assert client.get_task(task_id).stats.episodes_completed == 0


def test_vector_checks_num_envs(client: tamrm.Client, task_id: str) -> None:
    make_task(client, task_id)
    with client.session(task_id, 2) as session, pytest.raises(ValueError, match="num_envs"):
        tamrm.gym.VectorShapedReward(_vector_env(AutoresetMode.NEXT_STEP, 3), session)


def test_shaped_reward_continuous_pendulum(client: tamrm.Client, task_id: str) -> None:
    task = client.create_task(task_id, action_dim=1, pool_capacity=3, min_pool_size=1, start_step=0)
    cfg = RefConfig.of(task.config)
    ref = RefPool(cfg)
    stream = RefStream(ref, 1)
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(gym.make("Pendulum-v1", max_episode_steps=12), session)
        env.action_space.seed(0)
        for episode in range(4):
            env.reset(seed=episode)
            done = False
            while not done:
                action = env.action_space.sample()
                _, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                want = stream.shape(
                    0, action.astype(np.float32), info["original_reward"], terminated, truncated
                )
                assert info["knn_active"] == want["knn_active"]
                assert info["knn_reward"] == pytest.approx(want["knn_reward"], rel=1e-6, abs=1e-9)
                assert reward == pytest.approx(want["reward"], rel=1e-6)
                assert info["potential"] == 0.0
            assert truncated and not terminated
        env.close()
    pool = client.get_pool(task_id)
    assert [t.actions.shape for t in pool.trajectories] == [(12, 1)] * 3
    assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [
        (np.asarray(t.actions).tolist(), t.score) for t in ref.trajectories
    ]


def test_vector_shaped_reward_native_vector_env(client: tamrm.Client, task_id: str) -> None:
    """gymnasium's own CartPoleVectorEnv (make_vec's default for CartPole)."""
    make_task(client, task_id)
    envs = gym.make_vec("CartPole-v1", num_envs=4)
    with client.session(task_id, 4) as session:
        wrapped = tamrm.gym.VectorShapedReward(envs, session, value_fn=linear_value)
        wrapped.reset(seed=3)
        wrapped.action_space.seed(3)
        sent = 0
        ended = 0
        for _ in range(150):
            _, rewards, terminated, truncated, info = wrapped.step(wrapped.action_space.sample())
            sent += int(info["_potential"].sum())
            ended += int((terminated | truncated).sum())
            np.testing.assert_allclose(
                rewards[info["_potential"]],
                (info["original_reward"] + 0.6 * info["knn_reward"] + 0.4 * info["potential"])[
                    info["_potential"]
                ],
            )
        wrapped.close()
    stats = client.get_task(task_id).stats
    assert stats.steps_shaped == sent
    assert 0 < sent < 600  # the autoreset steps were not sent
    assert stats.episodes_completed == ended
