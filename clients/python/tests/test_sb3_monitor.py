"""SB3 episode statistics stay raw wherever the monitor sits."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import (
    DummyVecEnv,
    VecCheckNan,
    VecFrameStack,
    VecMonitor,
    VecNormalize,
)

import tamrm.sb3

torch.set_num_threads(1)

# Large shaping terms so that shaped and raw returns differ clearly.
SHAPING = dict(num_actions=2, alpha=5.0, beta=1.0, k=2, start_step=1, min_pool_size=2)


def test_vec_monitor_above_is_refused(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2), session)
        with pytest.raises(ValueError, match=r"ShapedVecEnv\(VecMonitor\(venv\), session\)"):
            VecMonitor(env)
        with pytest.raises(ValueError, match="VecMonitor above ShapedVecEnv"):
            VecMonitor(VecCheckNan(env))  # through another wrapper too


@pytest.mark.parametrize("monitor", ["Monitor", "VecMonitor"])
def test_episode_statistics_stay_raw(client: tamrm.Client, task_id: str, monitor: str) -> None:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    if monitor == "Monitor":
        venv = make_vec_env("CartPole-v1", n_envs=4, seed=0)  # a Monitor in each env
    else:
        import gymnasium as gym

        venv = VecMonitor(DummyVecEnv([lambda: gym.make("CartPole-v1")] * 4))
    with client.session(task_id, 4) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env, seed=0, device="cpu")
        env.bind_model(model)
        seen: list[dict] = []  # type: ignore[type-arg]
        from stable_baselines3.common.callbacks import BaseCallback

        class Grab(BaseCallback):
            def _on_step(self) -> bool:
                seen.extend(i for i in self.locals["infos"] if "episode" in i)
                return True

        model.learn(3000, callback=Grab())
    assert len(seen) > 20
    for info in seen:
        # CartPole's reward is 1 per step: a raw return equals the episode length.
        assert info["episode"]["r"] == pytest.approx(info["episode"]["l"])
        parts = info["shaped_episode"]
        assert parts["l"] == info["episode"]["l"]
        assert parts["r"] == pytest.approx(
            info["episode"]["r"] + parts["knn"] + parts["potential"], rel=1e-4, abs=1e-3
        )
    assert any(abs(i["shaped_episode"]["r"] - i["episode"]["r"]) > 1.0 for i in seen)
    # SB3's ep_rew_mean comes from these raw statistics.
    assert all(ep["r"] == pytest.approx(ep["l"]) for ep in model.ep_info_buffer)


def test_bind_model_warns_only_for_wrappers_that_change_observations(
    client: tamrm.Client, task_id: str
) -> None:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2), session)
        for outer in (VecCheckNan(env), VecNormalize(env, norm_obs=False), env):
            model = A2C("MlpPolicy", outer, device="cpu")
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                env.bind_model(model)
        for outer, name in (
            (VecNormalize(env), "VecNormalize"),
            (VecFrameStack(env, 2), "VecFrameStack"),
        ):
            model = A2C("MlpPolicy", outer, device="cpu")
            with pytest.warns(UserWarning, match=f"{name}, which change the observations"):
                env.bind_model(model)
        other = make_vec_env("CartPole-v1", n_envs=2)
        with pytest.warns(UserWarning, match="does not contain this ShapedVecEnv"):
            env.bind_model(A2C("MlpPolicy", other, device="cpu"))
        # The bound values are used: one step works.
        env.reset()
        env.step(np.array([0, 1]))
