"""SB3 checkpoints that carry the pool: training resumed from a checkpoint (the model and
its pool restored into a fresh task) shapes as if it had never stopped."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env

import tamrm.sb3

torch.set_num_threads(1)

CONFIG: dict[str, Any] = {"num_actions": 2, "pool_capacity": 6, "k": 3, "start_step": 2}
N_ENVS = 4
CHECKPOINT = 1000  # timesteps: the checkpoint compared, mid-training
TOTAL = 2000


def new_id() -> str:
    return f"sb3ckpt/{uuid.uuid4().hex}"


class CopyAtCheckpoint(BaseCallback):
    """At the checkpoint's step, a copy of the task as it is then, made by hand: the
    original task, continued from the checkpoint, as if training had never stopped."""

    def __init__(self, engine: tamrm.Engine, task_id: str, copy_id: str) -> None:
        super().__init__()
        self.engine, self.task_id, self.copy_id = engine, task_id, copy_id
        self.pool: tamrm.Pool | None = None

    def _on_step(self) -> bool:
        if self.num_timesteps == CHECKPOINT:
            self.pool = self.engine.get_pool(self.task_id)
            self.engine.create_task(self.copy_id, **CONFIG)
            for t in self.pool.trajectories:
                assert self.engine.add_trajectory(self.copy_id, t.actions, t.score).inserted
        return True


class Record(BaseCallback):
    """The actions sent and the shaped rewards returned, step by step."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.active = 0

    def _on_step(self) -> bool:
        # Copies: A2C adds the bootstrap of truncated episodes to ``rewards`` afterwards.
        loc = self.locals
        self.steps.append((loc["clipped_actions"].copy(), loc["rewards"].copy(), loc["dones"]))
        self.active += sum(int(info["knn_active"]) for info in loc["infos"])
        return True


def assert_same_trajectories(got: tamrm.Pool, want: tamrm.Pool) -> None:
    assert len(got) == len(want) > 0
    for g, w in zip(got.trajectories, want.trajectories, strict=True):
        assert g.score == w.score and g.actions.tobytes() == w.actions.tobytes()


def test_training_resumed_from_a_checkpoint_shapes_as_if_it_had_never_stopped(
    engine: tamrm.Engine, tmp_path: Path
) -> None:
    original, twin, restored = new_id(), new_id(), new_id()
    engine.create_task(original, **CONFIG)
    copy = CopyAtCheckpoint(engine, original, twin)
    with engine.session(original, N_ENVS) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=N_ENVS, seed=0), session)
        model = A2C("MlpPolicy", env, seed=0, device="cpu")
        saver = tamrm.sb3.PoolCheckpointCallback(
            CHECKPOINT // N_ENVS // 2, str(tmp_path), name_prefix="a2c"
        )
        model.learn(TOTAL, callback=CallbackList([saver, copy]))
    assert copy.pool is not None
    for steps in (CHECKPOINT // 2, CHECKPOINT, TOTAL):
        assert (tmp_path / f"a2c_{steps}_steps.zip").exists()
        assert (tmp_path / f"a2c_{steps}_steps.pool.jsonl").exists()
    checkpoint = tmp_path / f"a2c_{CHECKPOINT}_steps.zip"
    # Mid-training: the pool went on changing after the checkpoint.
    assert engine.get_task(original).stats.pool_version > copy.pool.pool_version

    task = tamrm.sb3.restore_pool(engine, checkpoint, task_id=restored)
    assert task.config == engine.get_task(original).config
    assert_same_trajectories(engine.get_pool(restored), copy.pool)

    # Resume: the checkpoint's model on the restored task, recorded step by step.
    record = Record()
    with engine.session(restored, N_ENVS) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=N_ENVS, seed=7), session)
        resumed = A2C.load(checkpoint, env=env, device="cpu")
        assert resumed.num_timesteps == CHECKPOINT
        env.seed(7)  # load seeded the envs with the model's seed; the replay's are these
        resumed.learn(400, reset_num_timesteps=False, callback=record)
    assert record.active > 100  # the pool shaped

    # The same steps into the original task as it was at the checkpoint: the same rewards.
    with engine.session(twin, N_ENVS) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=N_ENVS, seed=7), session)
        env.reset()
        for actions, shaped, dones in record.steps:
            _, rewards, replayed, _ = env.step(actions)
            assert np.array_equal(replayed, dones)  # the same episodes
            assert rewards.tobytes() == shaped.tobytes()
    assert_same_trajectories(engine.get_pool(twin), engine.get_pool(restored))


def test_the_pool_file_is_named_after_the_model() -> None:
    want = Path("ckpt/a2c_5000_steps.pool.jsonl")
    assert tamrm.sb3.pool_path("ckpt/a2c_5000_steps.zip") == want
    assert tamrm.sb3.pool_path(Path("ckpt/a2c_5000_steps")) == want
    assert tamrm.sb3.pool_path("best.v2.zip") == Path("best.v2.pool.jsonl")


def test_restore_pool(client: tamrm.Client | tamrm.Engine, tmp_path: Path) -> None:
    source, target = new_id(), new_id()
    client.create_task(source, num_actions=2, pool_capacity=3)
    client.add_trajectory(source, [0, 1, 1], 2.0)
    model = tmp_path / "m_10_steps.zip"
    with pytest.raises(FileNotFoundError, match=r"m_10_steps\.pool\.jsonl"):
        tamrm.sb3.restore_pool(client, model, task_id=target)
    client.export_pool(source, tamrm.sb3.pool_path(model))
    # A task of another config, with a pool: replaced, by default.
    client.create_task(target, num_actions=3)
    client.add_trajectory(target, [2], 1.0)
    task = tamrm.sb3.restore_pool(client, model, task_id=target)
    assert task.config == client.get_task(source).config and task.stats.pool_size == 1
    with pytest.raises(tamrm.FailedPrecondition):
        tamrm.sb3.restore_pool(client, model, task_id=target, replace=False)
    client.delete_task(source)
    assert tamrm.sb3.restore_pool(client, str(model)[:-4]).task_id == source


def test_the_callback_needs_a_shaped_vec_env(tmp_path: Path) -> None:
    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2), n_steps=5, device="cpu")
    callback = tamrm.sb3.PoolCheckpointCallback(1, str(tmp_path))
    with pytest.raises(ValueError, match="PoolCheckpointCallback: the model's env contains no"):
        model.learn(10, callback=callback)
