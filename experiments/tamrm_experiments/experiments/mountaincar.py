"""Mountain car (paper §V-B): DQN, -1 per step until the car reaches the flag."""

from __future__ import annotations

from typing import ClassVar

from tamrm_experiments.experiments.base import DQN_COMMON, Budget, ExperimentDef

__all__ = ["MOUNTAINCAR", "MountainCar"]


class MountainCar(ExperimentDef):
    """Mountain car: fewer total steps is better (the paper's Fig. 6)."""

    paper: ClassVar[dict[str, str]] = {
        "plain": "Fig. 6: more steps than TAMRM (no number given)",
        "pbrs": "Fig. 6: most steps (no number given)",
        "knn": "not run",
        "tamrm": "Fig. 6: fewest steps (no number given)",
    }
    claim: ClassVar[str] = "TAMRM needs fewer steps than plain DQN and DQN + PBRS"
    claim_check: ClassVar[str] = "TAMRM needs fewer steps than plain DQN"
    pbrs_claim: ClassVar[bool] = True


MOUNTAINCAR = MountainCar(
    name="mountaincar",
    title="Mountain car (DQN)",
    env="mountaincar",
    algo="dqn",
    algo_kwargs={
        **DQN_COMMON,
        "policy_kwargs": {"net_arch": [20, 20]},
        "buffer_size": 50_000,
        "learning_rate": 0.005,
    },
    tamrm={"pool_capacity": 20, "k": 20, "alpha": 1.0, "beta": 1.0, "gamma": 0.9},
    episodes=500,
    max_episode_steps=10_000,
    budgets={
        # 60 episodes: the kNN term starts once the pool of 20 is full (episode 21).
        "full": Budget(episodes=60, max_episode_steps=10_000, max_total_steps=70_000),
        # The paper's episode budget (still capped at 10 000 steps per episode).
        "paper": Budget(episodes=500, max_episode_steps=10_000, max_total_steps=1_000_000),
        "quick": Budget(episodes=3, max_episode_steps=400, max_total_steps=1_500),
    },
)
