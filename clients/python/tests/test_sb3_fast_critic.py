"""The native critic of ``model_value_fn``: torch's values, on views that follow training."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.torch_layers import FlattenExtractor

import tamrm.sb3

torch.set_num_threads(1)

# float32 weights, another summation order: equal up to float32 rounding.
RTOL, ATOL = 1e-5, 1e-6


def _torch_values(model: BaseAlgorithm, obs: np.ndarray) -> np.ndarray:
    """The reference: the model's own torch forward pass, as SB3 computes it."""
    return np.asarray(tamrm.sb3.model_value_fn(model, fast=False)(obs))


def _obs(model: BaseAlgorithm, rows: int, seed: int) -> np.ndarray:
    space = model.observation_space
    space.seed(seed)
    return np.stack([space.sample() for _ in range(rows)])


def _ppo(env: Any, **policy_kwargs: Any) -> PPO:
    return PPO(
        "MlpPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0, policy_kwargs=policy_kwargs
    )


MODELS: dict[str, Any] = {
    "a2c-tanh": lambda env: A2C("MlpPolicy", env, n_steps=5, seed=0),
    "ppo-relu-separate": lambda env: _ppo(
        env,
        activation_fn=torch.nn.ReLU,
        net_arch=dict(pi=[32], vf=[48, 16]),
        share_features_extractor=False,
    ),
    "ppo-linear-critic": lambda env: _ppo(env, net_arch=dict(pi=[8], vf=[])),
    "dqn": lambda env: DQN(
        "MlpPolicy", env, learning_starts=50, train_freq=1, buffer_size=500, seed=0
    ),
}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_native_critic_equals_torch_and_follows_training(name: str) -> None:
    env = make_vec_env("CartPole-v1", n_envs=4, seed=0)
    model = MODELS[name](env)
    value_fn = tamrm.sb3.model_value_fn(model)
    assert value_fn.native
    for rows in (1, 4, 16):
        obs = _obs(model, rows, seed=rows)
        got, want = value_fn(obs), _torch_values(model, obs)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)
    obs = _obs(model, 8, seed=1)
    before = value_fn(obs).copy()
    model.learn(400)  # in-place optimizer steps: the views see them, no rebuild needed
    after = value_fn(obs)
    assert not np.allclose(after, before, rtol=0, atol=1e-7), "training moved no weight"
    np.testing.assert_allclose(after, _torch_values(model, obs), rtol=RTOL, atol=ATOL)


def test_replaced_parameters_and_policies_are_followed() -> None:
    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=0), seed=0)
    value_fn = tamrm.sb3.model_value_fn(model)
    obs = _obs(model, 5, seed=2)
    value_fn(obs)
    # A parameter given new storage (``.data = ...``): the old views would be stale.
    layer = model.policy.value_net
    layer.weight.data = torch.randn_like(layer.weight) * 3.0
    np.testing.assert_allclose(value_fn(obs), _torch_values(model, obs), rtol=RTOL, atol=ATOL)
    # A new policy object (e.g. a model loaded from disk into the same algorithm object).
    other = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=1), seed=7)
    model.policy = other.policy
    np.testing.assert_allclose(value_fn(obs), _torch_values(other, obs), rtol=RTOL, atol=ATOL)


class OneHotObs(gym.ObservationWrapper[Any, Any, Any]):
    """CartPole whose observation is a Discrete index: SB3 one-hot encodes it."""

    def __init__(self, env: gym.Env[Any, Any]) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Discrete(5)

    def observation(self, observation: Any) -> int:
        return int(abs(observation[0]) * 10) % 5


class Scaled(FlattenExtractor):
    """A features extractor of the user's own (here: scaled observations)."""

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return super().forward(observations) * 0.5


UNSUPPORTED: dict[str, Any] = {
    "elu-activation": lambda: A2C(
        "MlpPolicy",
        make_vec_env("CartPole-v1", n_envs=2, seed=0),
        seed=0,
        policy_kwargs=dict(activation_fn=torch.nn.ELU),
    ),
    "discrete-observations": lambda: A2C(
        "MlpPolicy",
        make_vec_env(lambda: OneHotObs(gym.make("CartPole-v1")), n_envs=2, seed=0),
        seed=0,
    ),
    "custom-extractor": lambda: A2C(
        "MlpPolicy",
        make_vec_env("CartPole-v1", n_envs=2, seed=0),
        seed=0,
        policy_kwargs=dict(features_extractor_class=Scaled),
    ),
}


def _assert_torch_bit_for_bit(model: BaseAlgorithm, value_fn: tamrm.sb3.ModelValueFn) -> None:
    assert not value_fn.native
    obs = _obs(model, 6, seed=3)
    tensor, _ = model.policy.obs_to_tensor(obs)
    with torch.no_grad():
        want = model.policy.predict_values(tensor).cpu().numpy().reshape(-1)
    np.testing.assert_array_equal(value_fn(obs), want.astype(np.float64))


@pytest.mark.parametrize("name", sorted(UNSUPPORTED))
def test_other_policies_go_through_torch_exactly(name: str) -> None:
    model = UNSUPPORTED[name]()
    _assert_torch_bit_for_bit(model, tamrm.sb3.model_value_fn(model))


def test_fast_false_is_torch_bit_for_bit() -> None:
    model = PPO("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=0), n_steps=32, seed=0)
    _assert_torch_bit_for_bit(model, tamrm.sb3.model_value_fn(model, fast=False))


@pytest.mark.parametrize("fast", [True, False])
def test_bind_model_chooses_the_evaluation(client: tamrm.Client, task_id: str, fast: bool) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2, seed=0), session)
        model = A2C("MlpPolicy", env, seed=0)
        env.bind_model(model, fast=fast)
        assert isinstance(env.value_fn, tamrm.sb3.ModelValueFn)
        assert env.value_fn.native is fast
        model.learn(50)
        env.close()
