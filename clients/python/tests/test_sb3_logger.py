"""ShapingLogger: the shaped reward's parts in SB3's logger (CSV here), per row."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import tamrm

pytest.importorskip("stable_baselines3")
import torch
from stable_baselines3 import A2C
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

import tamrm.sb3

torch.set_num_threads(1)

ALPHA, BETA = 0.5, 1.0
SHAPING = dict(
    num_actions=2, alpha=ALPHA, beta=BETA, k=2, start_step=3, min_pool_size=3, pool_capacity=6
)
KEYS = ("reward_env", "knn_term", "potential_term", "knn_active_frac", "pool_size")


class AngleReward(gym.Wrapper[Any, Any, Any, Any]):
    """CartPole with a reward that varies from step to step: 1 + the pole angle."""

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, _, terminated, truncated, info = self.env.step(action)
        return obs, 1.0 + float(obs[2]), terminated, truncated, info


class Rollouts(BaseCallback):
    """Per rollout: every env step's (R, alpha*r, beta*F, knn_active), the pool size."""

    def __init__(self, pool_size: Any) -> None:
        super().__init__()
        self.pool_size = pool_size
        self.rollouts: list[tuple[np.ndarray, int]] = []
        self._steps: list[tuple[float, float, float, float]] = []

    def _on_rollout_start(self) -> None:
        self._steps = []

    def _on_step(self) -> bool:
        self._steps.extend(
            (i["original_reward"], ALPHA * i["knn_reward"], BETA * i["potential"], i["knn_active"])
            for i in self.locals["infos"]
        )
        return True

    def _on_rollout_end(self) -> None:
        self.rollouts.append((np.array(self._steps, dtype=np.float64), self.pool_size()))


@pytest.mark.parametrize("log_interval", [1, 4])
def test_csv_rows_hold_the_means_since_the_last_row(
    client: tamrm.Client,
    task_id: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    log_interval: int,
) -> None:
    client.create_task(task_id, **SHAPING)  # type: ignore[arg-type]
    get_task = client.get_task
    asked: list[str] = []

    def counting_get_task(task: str) -> tamrm.Task:
        asked.append(task)
        return get_task(task)

    monkeypatch.setattr(client, "get_task", counting_get_task)
    venv = make_vec_env(lambda: AngleReward(gym.make("CartPole-v1")), n_envs=4, seed=0)
    with client.session(task_id, 4) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env, n_steps=5, seed=0)
        model.set_logger(configure(str(tmp_path), ["csv"]))
        env.bind_model(model)
        env.reset()
        env.step(np.zeros(4, dtype=np.int64))  # before learn(): not in the rows
        rollouts = Rollouts(lambda: get_task(task_id).stats.pool_size)
        model.learn(2000, callback=[tamrm.sb3.ShapingLogger(), rollouts], log_interval=log_interval)
        env.close()

    with open(tmp_path / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rollouts.rollouts) == 100
    assert len(rows) == 100 // log_interval
    for j, row in enumerate(rows):
        covered = rollouts.rollouts[j * log_interval : (j + 1) * log_interval]
        steps = np.concatenate([parts for parts, _ in covered])
        assert len(steps) == 20 * log_interval
        means = steps.mean(axis=0)
        got = [float(row[f"tamrm/{key}"]) for key in KEYS]
        assert got[:4] == pytest.approx(means.tolist(), rel=1e-9, abs=1e-12)
        assert 0.0 <= got[3] <= 1.0
        assert got[4] == covered[-1][1]  # the pool size at the row's last rollout end
    column = {key: [float(row[f"tamrm/{key}"]) for row in rows] for key in KEYS}
    assert column["knn_active_frac"][0] == 0.0  # the pool starts empty
    assert max(column["knn_active_frac"]) > 0.5
    assert any(v != 0.0 for v in column["knn_term"])
    assert any(v != 0.0 for v in column["potential_term"])
    assert len(set(column["reward_env"])) > 1
    assert column["pool_size"][-1] == SHAPING["pool_capacity"]
    # The pool size is asked only when the pool version changed since the last ask.
    assert 0 < len(asked) < len(rollouts.rollouts)


def test_needs_a_shaped_vec_env(client: tamrm.Client, task_id: str) -> None:
    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2), n_steps=5)
    with pytest.raises(ValueError, match="contains no ShapedVecEnv"):
        model.learn(10, callback=tamrm.sb3.ShapingLogger())
