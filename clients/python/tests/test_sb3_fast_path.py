"""ShapedVecEnv's fast path (one native call per step) equals its general path, bit for bit."""

from __future__ import annotations

import warnings
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
        self.fast_steps = 0  # the fast path's count, set by _run
        self.critic_rows = 0  # observation rows its critic evaluated, set by _run

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
        model.learn(800, callback=record)
        record.fast_steps = env._vec_step.steps
        record.critic_rows = env._vec_step.critic_rows
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
        # V(s') of a step is V(s) of the next while the weights stay the same: between
        # two updates (A2C: every 5 steps; PPO: every 32) each observation is evaluated
        # once, so far fewer rows than the 2 per env and step of evaluating both.
        if algo in ("a2c", "ppo"):
            per_step = fast.critic_rows / (4 * fast.fast_steps)
            assert 1.0 < per_step < (1.3 if algo == "a2c" else 1.1)


def _twins(client: tamrm.Client, task_id: str, value_fn: str) -> tuple[Any, ...]:
    """A model and two ShapedVecEnvs on identical CartPoles and tasks, the first on the
    fast path, the second on the general path, both with the model's values (``"model"``),
    a plain function's (``"function"``) or none."""
    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=3, seed=5), seed=2)
    envs = []
    for fast in (True, False):
        tid = f"{task_id}-{'fast' if fast else 'slow'}"
        client.create_task(tid, num_actions=2, pool_capacity=3, k=2, min_pool_size=1)
        venv = make_vec_env("CartPole-v1", n_envs=3, seed=9, env_kwargs={"max_episode_steps": 12})
        env = tamrm.sb3.ShapedVecEnv(venv, client.session(tid, 3))
        env._fast_path = fast
        if value_fn == "model":
            with warnings.catch_warnings():  # the model's own env is another one
                warnings.simplefilter("ignore")
                env.bind_model(model)
        elif value_fn == "function":
            env.value_fn = lambda obs: np.asarray(obs, dtype=np.float64)[:, 0] * 3.0
        env.reset()
        envs.append(env)
    return model, envs[0], envs[1]


@pytest.mark.parametrize("value_fn", ["model", "function", "none"])
def test_fast_path_follows_changed_weights_policies_and_resets(
    client: tamrm.Client, task_id: str, value_fn: str
) -> None:
    model, fast, slow = _twins(client, task_id, value_fn)
    rng = np.random.default_rng(0)

    def step_both(times: int) -> None:
        for _ in range(times):
            actions = rng.integers(0, 2, size=3)
            a, b = fast.step(actions), slow.step(actions)
            assert a[1].tobytes() == b[1].tobytes()  # R_meta, bit for bit
            assert a[2].tolist() == b[2].tolist()
            assert [{k: i.get(k) for k in INFO_KEYS} for i in a[3]] == [
                {k: i.get(k) for k in INFO_KEYS} for i in b[3]
            ]

    step_both(20)  # episodes end (terminated or truncated at 12 steps)
    with torch.no_grad():  # an in-place update, as an optimizer's: V(s) is evaluated again
        for p in model.policy.value_net.parameters():
            p.add_(0.25)
    step_both(3)
    layer = model.policy.value_net  # new storage: the native critic is built again
    layer.weight.data = torch.randn_like(layer.weight) * 2.0
    step_both(3)
    model.policy = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=3), seed=4).policy
    step_both(3)
    fast.reset()
    slow.reset()
    step_both(10)
    # Every step took the fast path but those with a plain function as value_fn.
    assert fast._vec_step.steps == (0 if value_fn == "function" else 39)
    assert slow._vec_step.steps == 0
    if value_fn == "model":
        assert any(i["potential"] != 0.0 for i in fast.step(np.zeros(3, dtype=np.int64))[3])
    fast.close()
    slow.close()


def test_a_replaced_session_is_the_one_both_paths_step(client: tamrm.Client, task_id: str) -> None:
    _, fast, slow = _twins(client, task_id, "model")
    rng = np.random.default_rng(3)
    for env in (fast, slow):
        env.step(np.zeros(3, dtype=np.int64))
    old = [fast.session, slow.session]
    new = []
    for env, name in ((fast, "fast"), (slow, "slow")):
        tid = f"{task_id}-{name}-2"
        client.create_task(tid, num_actions=2, pool_capacity=3, k=2, min_pool_size=1)
        env.session = client.session(tid, 3)
        new.append(env.session)
    for _ in range(15):
        actions = rng.integers(0, 2, size=3)
        a, b = fast.step(actions), slow.step(actions)
        assert a[1].tobytes() == b[1].tobytes()
    # The new sessions were stepped, the fast one on the fast path.
    assert all(s.episodes_in_progress.all() for s in new)
    assert fast._vec_step.steps == 15
    other = client.session(f"{task_id}-fast-2", 2)
    with pytest.raises(ValueError, match="num_envs=2"):
        fast.session = other
    assert fast.session is new[0]
    for s in (*old, other):
        s.close()
    fast.close()
    slow.close()


def test_fast_path_errors_are_the_sessions(client: tamrm.Client, task_id: str) -> None:
    _, fast, slow = _twins(client, task_id, "model")
    for env in (fast, slow):
        env.step(np.zeros(3, dtype=np.int64))
        env.session.close()
        with pytest.raises(tamrm.SessionClosed):
            env.step(np.zeros(3, dtype=np.int64))
        env.venv.close()
    # A critic answering inf: the session's check, the same on both paths, and nothing
    # was sent (the step can be made again once the critic is fixed).
    model, fast, slow = _twins(client, task_id + "-2", "model")
    bias = model.policy.value_net.bias
    errors = []
    for env in (fast, slow):
        env.step(np.zeros(3, dtype=np.int64))
        with torch.no_grad():
            saved = bias.clone()
            bias.fill_(float("inf"))
        with pytest.raises(tamrm.InvalidArgument) as info:
            env.step(np.zeros(3, dtype=np.int64))
        errors.append(str(info.value))
        with torch.no_grad():
            bias.copy_(saved)
        assert not env.session.closed
        env.step(np.zeros(3, dtype=np.int64))
        env.close()
    assert errors[0] == errors[1]
    assert "values[0] = inf is not finite" in errors[0]


def test_fast_path_over_subprocesses_equals_the_general_path(
    client: tamrm.Client, task_id: str
) -> None:
    """SubprocVecEnv hands back its infos as a tuple and its rewards as float64: the fast
    path takes those steps too, with the general path's results (over a DummyVecEnv)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    runs = []
    for fast, vec_env_cls in ((True, SubprocVecEnv), (False, DummyVecEnv)):
        tid = f"{task_id}-{'fast' if fast else 'slow'}"
        client.create_task(tid, num_actions=2, pool_capacity=3, k=2, min_pool_size=1)
        venv = make_vec_env(
            "CartPole-v1",
            n_envs=2,
            seed=3,
            env_kwargs={"max_episode_steps": 20},
            vec_env_cls=vec_env_cls,
        )
        with client.session(tid, 2) as session:
            env = tamrm.sb3.ShapedVecEnv(venv, session)
            env._fast_path = fast
            model = A2C("MlpPolicy", env, n_steps=5, seed=1)
            env.bind_model(model)
            record = Record(env)
            model.learn(300, callback=record)
            runs.append((record, env._vec_step.steps, model))
            env.close()
    (fast_record, fast_steps, fast_model), (slow_record, slow_steps, slow_model) = runs
    assert fast_record.steps == slow_record.steps
    assert fast_record.stats == slow_record.stats
    assert fast_steps == len(fast_record.steps) >= 150 and slow_steps == 0
    assert any("shaped_episode" in info for _, info in fast_record.steps)
    for p, q in zip(fast_model.policy.parameters(), slow_model.policy.parameters(), strict=True):
        assert torch.equal(p, q)
