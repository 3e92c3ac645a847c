"""Stable-Baselines3 training through ShapedVecEnv, against the real server."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C, DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv

import tamrm.sb3

torch.set_num_threads(1)


def _check_one_step_uses_model_values(env: tamrm.sb3.ShapedVecEnv, model, q: bool) -> None:  # type: ignore[no-untyped-def]
    """After training: F of one step equals gamma*V(s') - V(s) from the model's own net."""
    gamma = env.session.config.gamma
    obs = env.reset()
    actions = np.array([env.action_space.sample() for _ in range(env.num_envs)])
    next_obs, rewards, dones, infos = env.step(actions)
    with torch.no_grad():
        if q:
            v = model.q_net(model.policy.obs_to_tensor(obs)[0]).max(dim=1).values.numpy()
            v_next_all = [
                model.q_net(
                    model.policy.obs_to_tensor(
                        infos[i].get("terminal_observation", next_obs[i])[None]
                    )[0]
                )
                .max(dim=1)
                .values.numpy()[0]
                for i in range(env.num_envs)
            ]
        else:
            v = model.policy.predict_values(model.policy.obs_to_tensor(obs)[0]).numpy()[:, 0]
            v_next_all = [
                model.policy.predict_values(
                    model.policy.obs_to_tensor(
                        infos[i].get("terminal_observation", next_obs[i])[None]
                    )[0]
                ).numpy()[0, 0]
                for i in range(env.num_envs)
            ]
    for i, info in enumerate(infos):
        terminated = dones[i] and not info.get("TimeLimit.truncated", False)
        v_next = 0.0 if terminated else float(np.float32(v_next_all[i]))
        expected = gamma * v_next - float(np.float32(v[i]))
        assert info["potential"] == pytest.approx(expected, rel=1e-4, abs=1e-4)
        assert rewards[i] == pytest.approx(
            info["original_reward"]
            + env.session.config.alpha * info["knn_reward"]
            + env.session.config.beta * info["potential"],
            rel=1e-5,
            abs=1e-5,
        )


@pytest.mark.parametrize("algo", ["dqn", "a2c"])
def test_training_fills_the_pool(client: tamrm.Client, task_id: str, algo: str) -> None:
    capacity = 10
    client.create_task(task_id, num_actions=2, pool_capacity=capacity, start_step=5)
    n_envs = 2 if algo == "dqn" else 4
    steps = 3000
    venv = make_vec_env("CartPole-v1", n_envs=n_envs, seed=0)
    with client.session(task_id, n_envs) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        if algo == "dqn":
            model = DQN("MlpPolicy", env, learning_starts=500, train_freq=4, seed=0, device="cpu")
        else:
            model = A2C("MlpPolicy", env, seed=0, device="cpu")
        assert model.get_env() is env
        env.bind_model(model)
        model.learn(total_timesteps=steps)
        shaped_steps = model.num_timesteps
        _check_one_step_uses_model_values(env, model, q=algo == "dqn")
        env.close()
    stats = client.get_task(task_id).stats
    assert shaped_steps >= steps
    assert stats.steps_shaped == shaped_steps + n_envs  # + the check's step
    assert stats.pool_size == capacity
    assert stats.episodes_completed > capacity
    assert stats.min_length >= 8  # CartPole episodes last at least 8 steps
    pool = client.get_pool(task_id)
    assert len(pool) == capacity
    # The stored scores are episode returns (the original reward, 1 per step).
    for traj in pool.trajectories:
        assert traj.score == len(traj)


def test_terminal_observation_and_truncation(client: tamrm.Client, task_id: str) -> None:
    """V(s') comes from infos['terminal_observation']; TimeLimit.truncated => truncated."""
    client.create_task(task_id, num_actions=2, gamma=0.9, beta=1.0, alpha=0.0)
    calls: list[np.ndarray] = []

    def value_fn(obs: np.ndarray) -> np.ndarray:
        calls.append(np.array(obs))
        return np.asarray(obs, dtype=np.float64)[:, 2] * 10.0 + 1.0

    def f32_value(o: np.ndarray) -> float:
        return float(np.float32(float(o[2]) * 10.0 + 1.0))

    venv = DummyVecEnv([lambda: gym.make("CartPole-v1", max_episode_steps=18) for _ in range(3)])
    venv.seed(3)
    kinds = {"terminated": 0, "truncated": 0}
    with client.session(task_id, 3) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session, value_fn=value_fn)
        obs = env.reset()
        rng = np.random.default_rng(0)
        for _ in range(150):
            actions = rng.integers(0, 2, size=3)
            next_obs, rewards, dones, infos = env.step(actions)
            batch = calls[-1]
            assert batch.shape == (6, 4)
            np.testing.assert_array_equal(batch[:3], obs)
            for i in range(3):
                v = f32_value(obs[i])
                if dones[i]:
                    final = infos[i]["terminal_observation"]
                    np.testing.assert_array_equal(batch[3 + i], final)
                    assert not np.array_equal(final, next_obs[i])
                    truncated = infos[i].get("TimeLimit.truncated", False)
                    kinds["truncated" if truncated else "terminated"] += 1
                    v_next = f32_value(final) if truncated else 0.0
                else:
                    np.testing.assert_array_equal(batch[3 + i], next_obs[i])
                    v_next = f32_value(next_obs[i])
                assert infos[i]["potential"] == pytest.approx(0.9 * v_next - v, rel=1e-6)
                assert rewards[i] == pytest.approx(1.0 + infos[i]["potential"], rel=1e-5)
                assert rewards.dtype == np.float32
            obs = next_obs
        env.close()
    assert kinds["terminated"] > 0 and kinds["truncated"] > 0, kinds


def test_model_value_fn_rejects_unknown_models() -> None:
    class Policy:
        pass

    class Model:
        policy = Policy()

    with pytest.raises(TypeError, match="value_fn"):
        tamrm.sb3.model_value_fn(Model())


def test_ppo_continuous_actions(client: tamrm.Client, task_id: str) -> None:
    """A continuous task: Box actions go to the server as action vectors."""
    from stable_baselines3 import PPO

    client.create_task(task_id, action_dim=1, pool_capacity=4, start_step=0)
    venv = make_vec_env("Pendulum-v1", n_envs=2, seed=0, env_kwargs={"max_episode_steps": 40})
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = PPO("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
        env.bind_model(model)
        model.learn(total_timesteps=256)
        env.close()
    stats = client.get_task(task_id).stats
    assert stats.steps_shaped == model.num_timesteps
    pool = client.get_pool(task_id)
    assert len(pool) == 4
    assert all(
        t.actions.shape == (40, 1) and t.actions.dtype == np.float32 for t in pool.trajectories
    )
    # The actions sent are the clipped ones SB3 passes to the env: within the Box.
    assert all(np.abs(t.actions).max() <= 2.0 for t in pool.trajectories)
