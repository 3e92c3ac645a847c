"""ShapedVecEnv's fast path (one native call per step) equals its general path, bit for bit."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import tamrm.gym
import tamrm.sb3

torch.set_num_threads(1)

INFO_KEYS = (*tamrm.gym.INFO_KEYS, "shaped_episode")


class Record(BaseCallback):
    """Every step's rewards and shaping infos, and the stats at every rollout end."""

    def __init__(self, env: tamrm.sb3.ShapedVecEnv) -> None:
        super().__init__()
        self.env = env
        self.steps: list[tuple[Any, ...]] = []
        self.stats: list[tamrm.sb3.ShapingStats] = []
        self.fast_steps = 0  # counted by _run

    def _on_step(self) -> bool:
        rewards = np.array(self.locals["rewards"])
        assert rewards.dtype == np.float32
        infos = [{k: i[k] for k in INFO_KEYS if k in i} for i in self.locals["infos"]]
        self.steps.append((rewards.tobytes(), repr(infos)))
        return True

    def _on_rollout_end(self) -> None:
        self.stats.append(self.env.take_stats())


def _run(
    client: tamrm.Client, task_id: str, algo: str, fast: bool, values: bool, env_id: str
) -> tuple[BaseAlgorithm, Record]:
    space = {"num_actions": 2} if env_id == "CartPole-v1" else {"action_dim": 1}
    shaping = dict(pool_capacity=4, k=3, start_step=2, min_pool_size=2, alpha=0.5, beta=0.7)
    client.create_task(task_id, **space, **shaping)  # type: ignore[arg-type]
    kwargs = {"max_episode_steps": 30}
    venv = make_vec_env(env_id, n_envs=4, seed=0, env_kwargs=kwargs)
    with client.session(task_id, 4) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        env._fast_path = fast
        if algo == "dqn":
            model: BaseAlgorithm = DQN(
                "MlpPolicy", env, learning_starts=50, train_freq=4, buffer_size=1000, seed=1
            )
        elif algo == "ppo":
            model = PPO("MlpPolicy", env, n_steps=32, batch_size=64, n_epochs=2, seed=1)
        else:
            model = A2C("MlpPolicy", env, n_steps=5, seed=1)
        if values:
            env.bind_model(model)
        record = Record(env)
        step_vec = session._step_vec

        def counting(*args: Any) -> Any:
            record.fast_steps += 1
            return step_vec(*args)

        session._step_vec = counting  # type: ignore[method-assign]
        model.learn(800, callback=record)
        env.close()
    return model, record


@pytest.mark.parametrize(
    ("algo", "values", "env_id"),
    [
        ("a2c", True, "CartPole-v1"),
        ("a2c", False, "CartPole-v1"),
        ("ppo", True, "CartPole-v1"),
        ("dqn", True, "CartPole-v1"),
        ("a2c", True, "Pendulum-v1"),
    ],
)
def test_fast_path_equals_the_general_path(
    client: tamrm.Client, task_id: str, algo: str, values: bool, env_id: str
) -> None:
    fast_model, fast = _run(client, task_id + "-fast", algo, True, values, env_id)
    slow_model, slow = _run(client, task_id + "-slow", algo, False, values, env_id)
    assert len(fast.steps) == len(slow.steps) >= 200
    assert fast.steps == slow.steps  # rewards bit for bit, infos alike (repr of floats)
    assert fast.stats == slow.stats
    for p, q in zip(fast_model.policy.parameters(), slow_model.policy.parameters(), strict=True):
        assert torch.equal(p, q)
    # Every step took the fast path, the steps where envs ended (terminated, or truncated
    # with V(s') of the terminal observation) included; the other run none.
    assert fast.fast_steps == len(fast.steps)
    assert slow.fast_steps == 0
    assert any("shaped_episode" in info for _, info in fast.steps)
    if values:
        assert any("'potential': 0.0" not in info for _, info in fast.steps)
