"""The maze (paper §V-C, Fig. 7): DQN, sparse reward +1 at the goal."""

from __future__ import annotations

from typing import Any, ClassVar

from tamrm_experiments.experiments.base import DQN_COMMON, Budget, ExperimentDef

__all__ = ["MAZE", "MAZE_SETUP", "Maze"]

#: What the maze and the modified maze share: environment, learner, shaping, budget.
MAZE_SETUP: dict[str, Any] = {
    "env": "maze",
    "algo": "dqn",
    "algo_kwargs": {
        **DQN_COMMON,
        "policy_kwargs": {"net_arch": [10, 10]},
        "buffer_size": 20_000,
        "learning_rate": 0.01,
    },
    "tamrm": {"pool_capacity": 10, "k": 10, "alpha": 0.8, "beta": 0.3, "gamma": 0.9},
    "episodes": 200,
    "max_episode_steps": 10_000,
    "score_from_info": True,
}


class Maze(ExperimentDef):
    """The maze: fewer total steps over the run is better (the paper's Table I)."""

    paper: ClassVar[dict[str, str]] = {
        "plain": "137,599",
        "pbrs": "1,433,215",
        "knn": "not run",
        "tamrm": "127,478",
    }
    claim: ClassVar[str] = "TAMRM needs fewer steps than plain DQN (-7%), PBRS about 10x more"
    claim_check: ClassVar[str] = "TAMRM needs fewer steps than plain DQN"
    pbrs_claim: ClassVar[bool] = True


MAZE = Maze(
    name="maze",
    title="Maze (DQN)",
    **MAZE_SETUP,
    budgets={
        # The paper's 200 episodes (its Table I gives total steps over 200 episodes); the
        # cap bounds a stuck run's compute (paper's PBRS arm: 1.43 M).
        "full": Budget(episodes=200, max_episode_steps=10_000, max_total_steps=600_000),
        "paper": Budget(episodes=200, max_episode_steps=10_000, max_total_steps=2_000_000),
        "quick": Budget(episodes=6, max_episode_steps=200, max_total_steps=1_500),
    },
)
