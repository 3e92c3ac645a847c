"""The bound critic is evaluated once per observation, bit for bit as if evaluated twice."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import numpy.typing as npt
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv

import tamrm.sb3

torch.set_num_threads(1)

SHAPING = dict(num_actions=2, alpha=0.5, beta=1.0, k=2, start_step=1, min_pool_size=2)
# Short episodes that end both ways: CartPole terminates, the time limit truncates.
ENV_KWARGS = {"max_episode_steps": 25}


class NaiveShapedVecEnv(tamrm.sb3.ShapedVecEnv):
    """The reference: V(s) and V(s') evaluated on every step, one batch each, no cache."""

    def _step_values(
        self,
        obs: Any,
        infos: list[dict[str, Any]],
        done_rows: list[int],
        truncated: npt.NDArray[np.bool_],
    ) -> dict[str, npt.NDArray[np.float64]]:
        assert self.value_fn is not None
        next_obs = np.array(obs, copy=True)
        for row in done_rows:
            next_obs[row] = infos[row]["terminal_observation"]
        v = np.asarray(self.value_fn(self._obs), dtype=np.float64)
        v_next = np.asarray(self.value_fn(next_obs), dtype=np.float64)
        key = "values" if v.ndim == 1 else "q_values"
        return {key: v, f"next_{key}": v_next}


class Counting:
    """Counts the calls of a value function; keeps its ``version`` (if it has one)."""

    def __init__(self, value_fn: Any) -> None:
        self.value_fn = value_fn
        self.calls = 0
        if hasattr(value_fn, "version"):
            self.version = value_fn.version

    def __call__(self, obs: Any) -> Any:
        self.calls += 1
        return self.value_fn(obs)


class Trace(BaseCallback):
    """Per step: the shaped rewards, F, the critic calls so far, whether the weights moved."""

    def __init__(self, counting: Counting) -> None:
        super().__init__()
        self.counting = counting
        self.rewards: list[np.ndarray] = []
        self.potentials: list[list[float]] = []
        self.calls: list[int] = []
        self.changed: list[bool] = []
        self.truncations: list[bool] = []
        self.terminations = 0
        self._params: torch.Tensor | None = None

    def _on_step(self) -> bool:
        params = torch.nn.utils.parameters_to_vector(self.model.policy.parameters()).clone()
        self.changed.append(self._params is None or not torch.equal(params, self._params))
        self._params = params
        infos = self.locals["infos"]
        self.rewards.append(np.array(self.locals["rewards"]))
        self.potentials.append([info["potential"] for info in infos])
        self.calls.append(self.counting.calls)
        ended = [i for i, done in enumerate(self.locals["dones"]) if done]
        truncated = [infos[i].get("TimeLimit.truncated", False) for i in ended]
        self.truncations.append(any(truncated))
        self.terminations += truncated.count(False)
        return True


def _model(algo: str, env: tamrm.sb3.ShapedVecEnv) -> BaseAlgorithm:
    if algo == "dqn":
        return DQN("MlpPolicy", env, learning_starts=100, train_freq=4, buffer_size=2000, seed=1)
    if algo == "ppo":
        return PPO("MlpPolicy", env, n_steps=32, batch_size=64, n_epochs=2, seed=1)
    return A2C("MlpPolicy", env, n_steps=5, seed=1)


def _train(
    client: tamrm.Client, task_id: str, algo: str, env_class: type[tamrm.sb3.ShapedVecEnv]
) -> tuple[BaseAlgorithm, Trace]:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    venv = make_vec_env("CartPole-v1", n_envs=4, seed=0, env_kwargs=ENV_KWARGS)
    with client.session(task_id, 4) as session:
        env = env_class(venv, session)
        model = _model(algo, env)
        env.bind_model(model)
        env.value_fn = counting = Counting(env.value_fn)
        trace = Trace(counting)
        model.learn(1000, callback=trace)
        env.close()
    return model, trace


@pytest.mark.parametrize("algo", ["a2c", "ppo", "dqn"])
def test_values_once_per_observation_bit_identical(
    client: tamrm.Client, task_id: str, algo: str
) -> None:
    model, trace = _train(client, task_id, algo, tamrm.sb3.ShapedVecEnv)
    naive_model, naive = _train(client, task_id + "-naive", algo, NaiveShapedVecEnv)

    steps = len(trace.calls)
    assert steps == len(naive.calls) >= 250
    # The same shaped rewards on every step: the same training, the same final weights.
    np.testing.assert_array_equal(np.array(trace.rewards), np.array(naive.rewards))
    assert trace.potentials == naive.potentials
    for p, q in zip(model.policy.parameters(), naive_model.policy.parameters(), strict=True):
        assert torch.equal(p, q)
    assert any(any(f != 0.0 for f in step) for step in trace.potentials)
    assert sum(trace.truncations) > 0 and trace.terminations > 0

    # The naive reference calls the critic twice per step; the cache once per step, plus
    # once for V(s) when the weights changed since the step before (the first step:
    # after reset), plus once for the real last observations of truncated episodes.
    assert naive.calls == [2 * (t + 1) for t in range(steps)]
    made = np.diff([0, *trace.calls])
    expected = 1 + np.array(trace.changed, dtype=int) + np.array(trace.truncations, dtype=int)
    np.testing.assert_array_equal(made, expected)
    assert trace.changed[0] and sum(trace.changed) > 5  # the weights did move in between
    assert trace.calls[-1] < 0.75 * naive.calls[-1]


class Versioned:
    """A fixed value function with a version the test bumps by hand."""

    def __init__(self, q: bool = False) -> None:
        self.q = q
        self.batches: list[np.ndarray] = []
        self.current = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.batches.append(np.array(obs))
        v = np.asarray(obs, dtype=np.float64)[:, 2] * 10.0 + 1.0 + self.current
        return np.stack([v, -v], axis=1) if self.q else v

    def version(self) -> int:
        return self.current


def _f32(x: float) -> float:
    return float(np.float32(x))


@pytest.mark.parametrize("q", [False, True], ids=["values", "q_values"])
def test_cache_follows_resets_truncations_and_versions(
    client: tamrm.Client, task_id: str, q: bool
) -> None:
    client.create_task(task_id, num_actions=2, gamma=0.9, beta=1.0, alpha=0.0)
    value_fn = Versioned(q)
    venv = DummyVecEnv([lambda: gym.make("CartPole-v1", max_episode_steps=18) for _ in range(3)])
    venv.seed(3)
    seen = {"terminated": 0, "truncated": 0, "bumped": 0}
    rng = np.random.default_rng(0)
    with client.session(task_id, 3) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session, value_fn=value_fn)
        obs = env.reset()
        for t in range(120):
            if t in (40, 80):
                obs = env.reset()  # the cached values are of the observations before
            if t % 15 == 7:
                value_fn.current += 1  # e.g. a gradient step: the cached values are stale
                seen["bumped"] += 1
            before = len(value_fn.batches)
            next_obs, _, dones, infos = env.step(rng.integers(0, 2, size=3))
            batches = value_fn.batches[before:]
            fresh = t in (0, 40, 80) or t % 15 == 7
            truncated = [
                i for i in range(3) if dones[i] and infos[i].get("TimeLimit.truncated", False)
            ]
            assert len(batches) == 1 + fresh + bool(truncated)
            if fresh:
                np.testing.assert_array_equal(batches.pop(0), obs)
            np.testing.assert_array_equal(batches.pop(0), next_obs)
            if truncated:
                final = batches.pop(0)
                for i in range(3):
                    expect = infos[i]["terminal_observation"] if i in truncated else next_obs[i]
                    np.testing.assert_array_equal(final[i], expect)
            for i in range(3):
                v = _f32(float(obs[i][2]) * 10.0 + 1.0 + value_fn.current)
                if dones[i]:
                    kind = "truncated" if i in truncated else "terminated"
                    seen[kind] += 1
                    final_obs = infos[i]["terminal_observation"]
                    v_next = _f32(float(final_obs[2]) * 10.0 + 1.0 + value_fn.current)
                    v_next = v_next if kind == "truncated" else 0.0
                else:
                    v_next = _f32(float(next_obs[i][2]) * 10.0 + 1.0 + value_fn.current)
                assert infos[i]["potential"] == pytest.approx(0.9 * v_next - v, rel=1e-6)
            obs = next_obs
        # Another value function: nothing cached from the first one is used.
        other = Versioned(q)
        env.value_fn = other
        env.step(np.zeros(3, dtype=np.int64))
        assert len(other.batches) == 2
        np.testing.assert_array_equal(other.batches[0], obs)
        env.close()
    assert seen["terminated"] > 0 and seen["truncated"] > 0, seen


def test_model_value_fn_version_moves_with_training(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2, seed=0), session)
        model = A2C("MlpPolicy", env, n_steps=5, seed=0)
        env.bind_model(model)
        value_fn = env.value_fn
        assert isinstance(value_fn, tamrm.sb3.ModelValueFn)
        before = value_fn.version()
        assert value_fn.version() == before  # stable while nothing changes
        obs = np.zeros((2, 4), dtype=np.float32)
        values = value_fn(obs)
        model.learn(10)  # two updates
        assert value_fn.version() != before
        assert not np.array_equal(value_fn(obs), values)
        after = value_fn.version()
        model.set_parameters({"policy": model.policy.state_dict()}, exact_match=False)
        assert value_fn.version() != after  # load_state_dict copies in place
        env.close()
