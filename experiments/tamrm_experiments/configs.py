"""Experiments, arms and budgets: every hyper-parameter of the reproduction in one place.

Where the paper (§V) gives a value it is used; where it is silent, the choice is written
next to it (and in ``docs/reproduction.md``). Every arm of an experiment uses the same
network, hyper-parameters and seeds; arms differ only in the shaping weights alpha, beta.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = [
    "ARMS",
    "EXPERIMENTS",
    "PROFILES",
    "Arm",
    "Budget",
    "Experiment",
    "RunSpec",
    "arm_weights",
    "make_specs",
]


@dataclass(frozen=True)
class Arm:
    """One arm: which of the two shaping terms is switched on."""

    name: str
    label: str
    knn: bool
    potential: bool


ARMS: dict[str, Arm] = {
    arm.name: arm
    for arm in (
        Arm("plain", "plain (no shaping)", knn=False, potential=False),
        Arm("pbrs", "PBRS only (alpha = 0)", knn=False, potential=True),
        Arm("knn", "kNN only (beta = 0)", knn=True, potential=False),
        Arm("tamrm", "TAMRM (kNN + PBRS)", knn=True, potential=True),
    )
}


@dataclass(frozen=True)
class Experiment:
    """One of the paper's experiments.

    Attributes:
        name: Short id (directory name of its runs).
        title: Human title.
        env: Environment factory key (see ``run.make_env``).
        algo: ``"a2c"`` or ``"dqn"`` (Stable-Baselines3).
        algo_kwargs: Keyword arguments of the SB3 algorithm (besides policy, env, seed).
        tamrm: Task configuration (pool_capacity, k, alpha, beta, gamma, ...) of the TAMRM
            arm; the other arms zero alpha and/or beta.
        episodes: The paper's episode budget.
        max_episode_steps: The per-episode step cap.
        switch_after: Modified maze: episodes after which the start moves and the
            shaping arms switch to a fresh task (pool).
        score_from_info: Send ``info["episode_score"]`` as the episode score.
    """

    name: str
    title: str
    env: str
    algo: str
    algo_kwargs: dict[str, Any]
    tamrm: dict[str, Any]
    episodes: int
    max_episode_steps: int
    switch_after: int | None = None
    score_from_info: bool = False


DQN_COMMON: dict[str, Any] = {
    # Paper: fixed epsilon 0.1 (the brief), "decay rate 0.9" read as the discount gamma
    # (the reward_decay of the tutorial DQN code the paper's Tkinter maze comes from).
    "exploration_initial_eps": 0.1,
    "exploration_final_eps": 0.1,
    "exploration_fraction": 1.0,
    "gamma": 0.9,
    # Paper silent: SB3 defaults, except the target network update (SB3's default of
    # 10 000 steps is longer than many whole runs here) and an earlier learning start.
    "batch_size": 32,
    "learning_starts": 200,
    "train_freq": 4,
    "gradient_steps": 1,
    "target_update_interval": 200,
}

EXPERIMENTS: dict[str, Experiment] = {
    exp.name: exp
    for exp in (
        Experiment(
            name="cartpole",
            title="Cart pole (A2C)",
            env="cartpole",
            algo="a2c",
            # Paper: actor and critic MLPs with two hidden layers of 20. Silent on the rest:
            # SB3 A2C defaults (lr 7e-4, n_steps 5, gamma 0.99, RMSprop, ent_coef 0).
            algo_kwargs={"policy_kwargs": {"net_arch": {"pi": [20, 20], "vf": [20, 20]}}},
            tamrm={"pool_capacity": 30, "k": 20, "alpha": 0.8, "beta": 0.8, "gamma": 0.99},
            episodes=1000,
            max_episode_steps=200,
        ),
        Experiment(
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
        ),
        Experiment(
            name="maze",
            title="Maze (DQN)",
            env="maze",
            algo="dqn",
            algo_kwargs={
                **DQN_COMMON,
                "policy_kwargs": {"net_arch": [10, 10]},
                "buffer_size": 20_000,
                "learning_rate": 0.01,
            },
            tamrm={"pool_capacity": 10, "k": 10, "alpha": 0.8, "beta": 0.3, "gamma": 0.9},
            episodes=200,
            max_episode_steps=10_000,
            score_from_info=True,
        ),
        Experiment(
            name="maze_modified",
            title="Modified maze (DQN, the start moves mid-run)",
            env="maze",
            algo="dqn",
            algo_kwargs={
                **DQN_COMMON,
                "policy_kwargs": {"net_arch": [10, 10]},
                "buffer_size": 20_000,
                "learning_rate": 0.01,
            },
            tamrm={"pool_capacity": 10, "k": 10, "alpha": 0.8, "beta": 0.3, "gamma": 0.9},
            episodes=200,
            max_episode_steps=10_000,
            switch_after=100,
            score_from_info=True,
        ),
    )
}


@dataclass(frozen=True)
class Budget:
    """Per-experiment budget of a profile (may be smaller than the paper's)."""

    episodes: int
    max_episode_steps: int
    #: Safety cap on a run's total environment steps: a run reaching it stops early and
    #: is reported as censored (its totals are lower bounds).
    max_total_steps: int
    switch_after: int | None = None


@dataclass(frozen=True)
class Profile:
    """A named set of budgets and a default number of seeds."""

    name: str
    seeds: int
    budgets: dict[str, Budget] = field(default_factory=dict)


PROFILES: dict[str, Profile] = {
    # What the committed docs/reproduction.md ran: the maze at the paper's budget, the
    # others reduced to fit the compute of a session on 2 cores (each environment step is
    # a gRPC round trip). The paper: cart pole 1000 episodes; mountain car 500; maze 200
    # (modified maze: start moves after 100).
    "full": Profile(
        name="full",
        seeds=5,
        budgets={
            "cartpole": Budget(episodes=500, max_episode_steps=200, max_total_steps=100_000),
            # 60 episodes: the kNN term starts once the pool of 20 is full (episode 21).
            "mountaincar": Budget(episodes=60, max_episode_steps=10_000, max_total_steps=70_000),
            # The maze at the paper's 200 episodes (its Table I gives total steps over 200
            # episodes); the cap bounds a stuck run's compute (paper's PBRS arm: 1.43 M).
            "maze": Budget(episodes=200, max_episode_steps=10_000, max_total_steps=600_000),
            # Half the paper's budget: the start moves after episode 50 (paper: 100).
            "maze_modified": Budget(
                episodes=100, max_episode_steps=10_000, max_total_steps=300_000, switch_after=50
            ),
        },
    ),
    # The paper's episode budgets (mountain car still capped at 10 000 steps per episode).
    "paper": Profile(
        name="paper",
        seeds=5,
        budgets={
            "cartpole": Budget(episodes=1000, max_episode_steps=200, max_total_steps=200_000),
            "mountaincar": Budget(
                episodes=500, max_episode_steps=10_000, max_total_steps=1_000_000
            ),
            "maze": Budget(episodes=200, max_episode_steps=10_000, max_total_steps=2_000_000),
            "maze_modified": Budget(
                episodes=200, max_episode_steps=10_000, max_total_steps=2_000_000, switch_after=100
            ),
        },
    ),
    "quick": Profile(
        name="quick",
        seeds=1,
        budgets={
            "cartpole": Budget(episodes=30, max_episode_steps=200, max_total_steps=3_000),
            "mountaincar": Budget(episodes=3, max_episode_steps=400, max_total_steps=1_500),
            "maze": Budget(episodes=6, max_episode_steps=200, max_total_steps=1_500),
            "maze_modified": Budget(
                episodes=6, max_episode_steps=200, max_total_steps=1_500, switch_after=3
            ),
        },
    ),
}


def arm_weights(experiment: Experiment, arm: Arm) -> tuple[float, float]:
    """Return (alpha, beta) of ``arm`` in ``experiment``."""
    alpha = float(experiment.tamrm["alpha"]) if arm.knn else 0.0
    beta = float(experiment.tamrm["beta"]) if arm.potential else 0.0
    return alpha, beta


@dataclass(frozen=True)
class RunSpec:
    """One run: (experiment, arm, seed) under a budget."""

    experiment: str
    arm: str
    seed: int
    profile: str
    budget: Budget

    @property
    def key(self) -> str:
        """``experiment/arm/seedN``: the run's id and relative path stem."""
        return f"{self.experiment}/{self.arm}/seed{self.seed}"

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able description (stored next to the run's CSV)."""
        exp = EXPERIMENTS[self.experiment]
        alpha, beta = arm_weights(exp, ARMS[self.arm])
        return {
            "experiment": self.experiment,
            "arm": self.arm,
            "seed": self.seed,
            "profile": self.profile,
            "budget": asdict(self.budget),
            "algo": exp.algo,
            "algo_kwargs": exp.algo_kwargs,
            "task_config": {**exp.tamrm, "alpha": alpha, "beta": beta},
        }


def make_specs(
    profile: str,
    seeds: int | None = None,
    experiments: list[str] | None = None,
    arms: list[str] | None = None,
    first_seed: int = 0,
) -> list[RunSpec]:
    """The run grid, seed-major (every experiment and arm of seed 0 first), so that a
    partial run has whole seeds across arms."""
    prof = PROFILES[profile]
    n = prof.seeds if seeds is None else seeds
    exps = experiments or list(EXPERIMENTS)
    arm_names = arms or list(ARMS)
    specs = []
    for seed in range(first_seed, n):
        for exp in exps:
            budget = prof.budgets[exp]
            for arm in arm_names:
                specs.append(RunSpec(exp, arm, seed, profile, budget))
    return specs
