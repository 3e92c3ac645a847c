"""Mountain car (paper §V-B): DQN, -1 per step until the car reaches the flag."""

from __future__ import annotations

from typing import ClassVar

from tamrm_experiments.experiments.base import (
    CLEAN_VARIANTS,
    DQN_COMMON,
    Budget,
    Claim,
    ExperimentDef,
    Variant,
)

__all__ = ["MOUNTAINCAR", "MountainCar"]


class MountainCar(ExperimentDef):
    """Mountain car: fewer total steps is better (the paper's Fig. 6)."""

    paper: ClassVar[dict[str, str]] = {
        "plain": "Fig. 6: more steps than TAMRM (no number given)",
        "pbrs": "Fig. 6: most steps (no number given)",
        "knn": "not run",
        "tamrm": "Fig. 6: fewest steps (no number given)",
    }
    claims: ClassVar[tuple[Claim, ...]] = (
        Claim(
            "TAMRM needs fewer total steps than plain over 500 episodes",
            "Fig. 6: TAMRM fewest steps (no number given)",
            "tamrm",
            "total_steps",
            -1,
        ),
    )


def _authors(sign: float) -> dict:
    return {
        "learner": "tutorial_dqn",
        "tamrm": {
            "pool_capacity": 20,
            "k": 20,
            "start_step": 10,
            "alpha": sign,
            "beta": sign,
            "gamma": 0.9,
        },
        "pbrs_beta": sign,
        "terminal_reward": 10.0,
    }


#: The authors' mountain car (``MountainCar_test/run_MountainCar.py``): their tutorial DQN
#: on the unwrapped ``MountainCar-v0`` (no 200-step limit); shaping
#: ``reward += -1 * predict_modified - 1 * (0.9 max Q_target(s') - max Q(s))`` while the
#: pool of 20 is full and 10 <= t < L_min - 1 (top 20); then ``if done: reward = 10``;
#: score = the return (-steps). ``authors-neg`` is their code's sign, ``authors-pos`` the
#: paper's (alpha = beta = +1). The episode cap is only a safety net (their first episodes
#: took ~30 000 random steps). The sign enters only through alpha, beta and ``pbrs_beta``,
#: all 0 in the plain arm: ``authors-pos`` uses the plain runs of ``authors-neg``.
AUTHORS_BUDGETS = {
    "paper": Budget(episodes=500, max_episode_steps=100_000, max_total_steps=3_000_000),
    "full": Budget(episodes=500, max_episode_steps=100_000, max_total_steps=3_000_000),
    "quick": Budget(episodes=2, max_episode_steps=300, max_total_steps=600),
}
AUTHORS_VARIANTS = (
    Variant(
        "authors-neg",
        "authors",
        "authors (their DQN, their signs: alpha = beta = -1)",
        _authors(-1.0),
        AUTHORS_BUDGETS,
    ),
    Variant(
        "authors-pos",
        "authors",
        "authors (their DQN, the paper's signs: alpha = beta = +1)",
        _authors(1.0),
        AUTHORS_BUDGETS,
        plain_from="authors-neg",
    ),
)

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
    variants=(*CLEAN_VARIANTS, *AUTHORS_VARIANTS),
)
