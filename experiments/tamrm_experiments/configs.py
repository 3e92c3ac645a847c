"""Experiments, arms and budgets: every hyper-parameter of the reproduction in one place.

Where the paper (§V) gives a value it is used; where it is silent, the choice is written
next to it (and in ``docs/reproduction.md``). Every arm of an experiment uses the same
network, hyper-parameters and seeds; arms differ only in the shaping weights alpha, beta.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from tamrm_experiments.experiments import EXPERIMENTS
from tamrm_experiments.experiments.base import ARMS, Arm, Budget
from tamrm_experiments.experiments.base import ExperimentDef as Experiment

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
class Profile:
    """A named set of budgets and a default number of seeds."""

    name: str
    seeds: int
    budgets: dict[str, Budget] = field(default_factory=dict)


#: The budget profiles; each experiment's module gives its budget in each. ``full`` is what
#: the first committed report ran (the maze at the paper's budget, the others reduced to fit
#: a session on 2 cores); ``paper`` is the paper's episode budgets; ``quick`` a smoke test.
PROFILES: dict[str, Profile] = {
    name: Profile(
        name=name,
        seeds=seeds,
        budgets={exp.name: exp.budgets[name] for exp in EXPERIMENTS.values()},
    )
    for name, seeds in (("full", 5), ("paper", 5), ("quick", 1))
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
