"""Experiments, arms and budgets: every hyper-parameter of the reproduction in one place.

Where the paper (§V) gives a value it is used; where it is silent, the choice is written
next to it (and in ``docs/reproduction.md``). Every arm of an experiment uses the same
network, hyper-parameters and seeds; arms differ only in the shaping weights alpha, beta.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

from tamrm_experiments.experiments import EXPERIMENTS
from tamrm_experiments.experiments.base import ARMS, FIDELITIES, Arm, Budget, Variant
from tamrm_experiments.experiments.base import ExperimentDef as Experiment

__all__ = [
    "ARMS",
    "EXPERIMENTS",
    "FIDELITIES",
    "PROFILES",
    "Arm",
    "Budget",
    "Experiment",
    "RunSpec",
    "Variant",
    "all_variants",
    "arm_weights",
    "make_specs",
    "plain_key",
    "runs_variant",
    "task_config",
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


def task_config(experiment: Experiment, variant: Variant, arm: Arm) -> dict[str, Any]:
    """The ``create_task`` settings of ``arm`` in ``variant`` of ``experiment``.

    Clean: the experiment's TAMRM configuration (SPEC defaults where it is silent), alpha
    and/or beta zeroed by the arm, ``gate_potential`` from the variant. Authors: their
    configuration, their PBRS-only line (``pbrs_beta``, every step: ungated) for the PBRS
    arm, and the potential term gated to the kNN window (their code adds both terms only
    there) in the TAMRM and kNN-only arms.
    """
    if variant.fidelity == "authors":
        base = dict(variant.settings["tamrm"])
        # Their code adds its terms only with a full pool.
        base["min_pool_size"] = base["pool_capacity"]
        alpha = float(base["alpha"]) if arm.knn else 0.0
        if arm.potential and not arm.knn:
            beta, gate = float(variant.settings["pbrs_beta"]), False
        else:
            beta, gate = (float(base["beta"]) if arm.potential else 0.0), True
        return {**base, "alpha": alpha, "beta": beta, "gate_potential": gate}
    alpha = float(experiment.tamrm["alpha"]) if arm.knn else 0.0
    beta = float(experiment.tamrm["beta"]) if arm.potential else 0.0
    gate = bool(variant.settings.get("gate_potential", False))
    return {**experiment.tamrm, "alpha": alpha, "beta": beta, "gate_potential": gate}


def arm_weights(experiment: Experiment, arm: Arm, variant: str = "clean") -> tuple[float, float]:
    """Return (alpha, beta) of ``arm`` in ``experiment`` (and ``variant``)."""
    cfg = task_config(experiment, experiment.variant(variant), arm)
    return cfg["alpha"], cfg["beta"]


#: Settings that only the shaping terms read: their weights alpha and beta (of the TAMRM
#: arm and, ``pbrs_beta``, of the PBRS arm), ``gate_potential``, and the pool and window of
#: the kNN term (``pool_capacity``, ``k``, ``start_step``, ``min_pool_size``). The plain arm
#: zeroes both terms, so its rewards, and so its runs, do not depend on them (only the
#: server's diagnostics of r(t), which plain does not use, do).
_SHAPING_ONLY = (
    "alpha",
    "beta",
    "pbrs_beta",
    "gate_potential",
    "pool_capacity",
    "k",
    "start_step",
    "min_pool_size",
)


def _without_shaping(settings: Any) -> Any:
    if isinstance(settings, dict):
        return {k: _without_shaping(v) for k, v in settings.items() if k not in _SHAPING_ONLY}
    return settings


def plain_key(experiment: Experiment, variant: Variant) -> str:
    """Everything the plain arm of ``variant`` depends on, as a canonical string: the
    fidelity, the budgets, the variant's settings and the plain task configuration, less
    the shaping-only settings. Two variants with equal keys have identical plain runs."""
    cfg = task_config(experiment, variant, ARMS["plain"])
    assert cfg["alpha"] == 0.0 and cfg["beta"] == 0.0, "the plain arm shapes nothing"
    budgets = {p: asdict(experiment.budget(p, variant.name)) for p in sorted(PROFILES)}
    return json.dumps(
        {
            "fidelity": variant.fidelity,
            "budgets": budgets,
            "settings": _without_shaping(variant.settings),
            "task_config": _without_shaping(cfg),
        },
        sort_keys=True,
    )


def _plain_variant(experiment: Experiment, variant: Variant) -> Variant:
    """The variant whose plain runs ``variant`` uses; raises if the two could differ."""
    if variant.plain_from is None:
        return variant
    source = experiment.variant(variant.plain_from)
    if source.plain_from is not None:
        raise ValueError(f"{experiment.name}/{source.name} shares its plain arm in turn")
    if plain_key(experiment, variant) != plain_key(experiment, source):
        raise ValueError(
            f"{experiment.name}/{variant.name} declares plain_from={source.name!r}, but its "
            "plain arm differs from that variant's in more than shaping settings"
        )
    return source


def runs_variant(experiment: Experiment, variant: str, arm: str) -> str:
    """The variant under whose name the runs of ``arm`` in ``variant`` are stored:
    ``variant`` itself, or for the plain arm the variant it shares plain with."""
    var = experiment.variant(variant)
    return _plain_variant(experiment, var).name if arm == "plain" else variant


@dataclass(frozen=True)
class RunSpec:
    """One run: (experiment, variant, arm, seed) under a budget."""

    experiment: str
    arm: str
    seed: int
    profile: str
    budget: Budget
    variant: str = "clean"

    @property
    def fidelity(self) -> str:
        """``"clean"`` or ``"authors"``."""
        return EXPERIMENTS[self.experiment].variant(self.variant).fidelity

    @property
    def key(self) -> str:
        """``experiment/variant/arm/seedN``: the run's id and relative path stem."""
        return f"{self.experiment}/{self.variant}/{self.arm}/seed{self.seed}"

    def task_config(self) -> dict[str, Any]:
        """The run's ``create_task`` settings."""
        exp = EXPERIMENTS[self.experiment]
        return task_config(exp, exp.variant(self.variant), ARMS[self.arm])

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able description (stored next to the run's CSV)."""
        exp = EXPERIMENTS[self.experiment]
        var = exp.variant(self.variant)
        out: dict[str, Any] = {
            "experiment": self.experiment,
            "fidelity": var.fidelity,
            "variant": self.variant,
            "arm": self.arm,
            "seed": self.seed,
            "profile": self.profile,
            "budget": asdict(self.budget),
        }
        if var.fidelity == "authors":
            out["algo"] = var.settings["learner"]
            out["variant_settings"] = var.settings
        else:
            out["algo"] = exp.algo
            out["algo_kwargs"] = exp.algo_kwargs
            out["variant_settings"] = var.settings
        out["task_config"] = self.task_config()
        return out


def make_specs(
    profile: str,
    seeds: int | None = None,
    experiments: list[str] | None = None,
    arms: list[str] | None = None,
    first_seed: int = 0,
    fidelities: list[str] | None = None,
    variants: list[str] | None = None,
) -> list[RunSpec]:
    """The run grid, seed-major (every experiment, variant and arm of seed 0 first), so
    that a partial run has whole seeds across arms. ``fidelities`` and ``variants`` select
    variants (by fidelity, by name); ``None`` means all."""
    prof = PROFILES[profile]
    n = prof.seeds if seeds is None else seeds
    exps = experiments or list(EXPERIMENTS)
    arm_names = arms or list(ARMS)
    specs: list[RunSpec] = []
    seen: set[str] = set()
    for seed in range(first_seed, n):
        for name in exps:
            exp = EXPERIMENTS[name]
            for var in exp.variants:
                if not var.runnable:
                    continue
                if fidelities and var.fidelity not in fidelities:
                    continue
                if variants and var.name not in variants:
                    continue
                budget = exp.budget(profile, var.name)
                for arm in arm_names:
                    owner = _plain_variant(exp, var) if arm == "plain" else var
                    spec = RunSpec(name, arm, seed, profile, budget, owner.name)
                    if spec.key not in seen:
                        seen.add(spec.key)
                        specs.append(spec)
    return specs


def all_variants() -> list[str]:
    """Every variant name of every experiment."""
    return sorted({v.name for e in EXPERIMENTS.values() for v in e.variants if v.runnable})
