"""The regime study's grid: stages, environment variants, arms, settings and seeds.

Everything the plan (docs/regimes/plan.md) fixes is here, in code, so that the runs are
what was registered. A run is a ``tamrm.trial`` run (the same learner, records and
metrics as ``tamrm-trial``), plus two arms the trial has no flag for: ``sil`` (the same
learner with self-imitation learning, no shaping) and ``oracle`` (the kNN term with a pool
loaded with shortest paths before learning).

Stages:
- ``pilot``: plain PPO only, to fix the caps, the DoorKey size and the budgets;
- ``tune``: on tuning seeds, the shaping grid (stage A, then stage B around A's best) and
  the SIL grid, on E1-det, E2-fixed and E3;
- ``confirm``: every arm on fresh paired seeds, settings frozen from ``tune`` by the rule
  in :func:`select`.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "ARMS",
    "BUDGET",
    "CONFIRM_SEEDS",
    "HYPERPARAMS",
    "TUNE_SEEDS",
    "VARIANTS",
    "RunKey",
    "Variant",
    "config_id",
    "sil_grid",
    "stage_a_grid",
    "stage_b_grid",
]

#: Every arm of the confirmation, in report order.
ARMS = ("plain", "pbrs", "knn", "tamrm", "sil", "oracle")

#: The learner: Stable-Baselines3 PPO with the Atari settings of the PPO paper (8 envs x
#: 128 steps per update, 4 epochs of 4 minibatches), for every environment. rl-zoo3's
#: MiniGrid settings (minibatches of 64, 10 epochs) learn in fewer timesteps but cost
#: 5 times the CPU per timestep here: the study could not have afforded its seeds.
ALGO = "ppo"
HYPERPARAMS: dict[str, Any] = {
    "n_envs": 8,
    "n_steps": 128,
    "batch_size": 256,
    "n_epochs": 4,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "learning_rate": 2.5e-4,
    "clip_range": 0.2,
    "ent_coef": 0.01,
}


@dataclass(frozen=True)
class Variant:
    """One environment variant: a registered id, its kwargs, its family and role."""

    name: str
    env: str
    kwargs: Mapping[str, Any]
    family: str
    #: Whether each seed gets its own fixed layout (``layout_seed`` = the run's seed).
    layout_per_seed: bool = False
    #: The variant the family's settings are tuned on (the others are controls).
    tuned_here: bool = False

    def env_kwargs(self, seed: int) -> dict[str, Any]:
        """The env's kwargs for a run with ``seed``."""
        out = dict(self.kwargs)
        if self.layout_per_seed:
            out["layout_seed"] = seed
        return out


#: DoorKey's size, fixed by the pilot (docs/regimes/plan.md).
DOORKEY_SIZE = 6

VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("E1-det", "TamrmRegimes/Maze-v0", {}, "E1", tuned_here=True),
        Variant("E1-sticky", "TamrmRegimes/Maze-v0", {"sticky": 0.25}, "E1"),
        Variant(
            "E2-fixed",
            "TamrmRegimes/DoorKey-v0",
            {"size": DOORKEY_SIZE},
            "E2",
            layout_per_seed=True,
            tuned_here=True,
        ),
        Variant("E2-proc", "TamrmRegimes/DoorKey-v0", {"size": DOORKEY_SIZE}, "E2"),
        Variant("E3", "TamrmRegimes/DecoyMaze-v0", {}, "E3", tuned_here=True),
    )
}

#: The pilot's variants: plain PPO on each environment, DoorKey in three sizes.
PILOT_VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        VARIANTS["E1-det"],
        VARIANTS["E1-sticky"],
        VARIANTS["E3"],
        *(
            Variant(
                f"pilot-E2-{kind}-{size}",
                "TamrmRegimes/DoorKey-v0",
                {"size": size},
                "E2",
                layout_per_seed=kind == "fixed",
            )
            for size in (5, 6, 8)
            for kind in ("fixed", "proc")
        ),
    )
}
PILOT_SEEDS = (2000, 2001, 2002, 2003)
PILOT_BUDGET = {"E1": 150_000, "E2": 300_000, "E3": 150_000}


def variant(name: str) -> Variant:
    """A variant of the confirmation or of the pilot, by name."""
    return VARIANTS.get(name) or PILOT_VARIANTS[name]


def pilot_keys() -> list[RunKey]:
    """The pilot: plain PPO on every pilot variant and seed."""
    return [RunKey("pilot", v, "plain", s) for s in PILOT_SEEDS for v in PILOT_VARIANTS]


#: Timesteps per run, per family (fixed by the pilot).
BUDGET = {"E1": 60_000, "E2": 100_000, "E3": 80_000}

#: Seeds: tuning seeds never appear in the confirmation.
TUNE_SEEDS = (1000, 1001, 1002)
CONFIRM_SEEDS = tuple(range(15))

#: The arms' shaping weights besides the tuned settings: pbrs and tamrm use SPEC's
#: default beta; knn and oracle have beta = 0, pbrs alpha = 0.
DEFAULT_BETA = 0.8


def _grid(**axes: Iterable[Any]) -> list[dict[str, Any]]:
    names = list(axes)
    return [dict(zip(names, values, strict=True)) for values in itertools.product(*axes.values())]


def stage_a_grid() -> list[dict[str, Any]]:
    """Stage A of the shaping grid (16 settings): alpha x min_pool_size x
    require_score_spread, at pool_capacity 20, k = 20, start_step 0."""
    out = []
    for row in _grid(alpha=(0.03, 0.1, 0.3, 0.8), min_pool=("1", "cap"), spread=(False, True)):
        out.append(
            {
                "alpha": row["alpha"],
                "pool_capacity": 20,
                "k": 20,
                "start_step": 0,
                "min_pool_size": 1 if row["min_pool"] == "1" else 20,
                "require_score_spread": row["spread"],
            }
        )
    return out


def stage_b_grid(best_a: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Stage B (8 settings) around stage A's best: pool_capacity {10, 40} x k {3, all} x
    start_step {0, 10}; alpha, require_score_spread and whether min_pool_size is 1 or
    the capacity are A's."""
    out = []
    full = best_a["min_pool_size"] == best_a["pool_capacity"]
    for row in _grid(capacity=(10, 40), k=("3", "all"), start=(0, 10)):
        cap = row["capacity"]
        out.append(
            {
                "alpha": best_a["alpha"],
                "pool_capacity": cap,
                "k": 3 if row["k"] == "3" else cap,
                "start_step": row["start"],
                "min_pool_size": cap if full else 1,
                "require_score_spread": best_a["require_score_spread"],
            }
        )
    return out


def sil_grid() -> list[dict[str, Any]]:
    """SIL's grid, as many settings as the shaping grid's two stages (24): updates per
    PPO update x value coefficient x loss weight x buffer capacity (x batch for the rest)."""
    out = _grid(
        sil_updates=(1, 4),
        sil_value_coef=(0.01, 0.1),
        sil_weight=(0.1, 1.0),
        sil_capacity=(10_000, 100_000),
    )
    out += [
        {**row, "sil_batch": 256}
        for row in _grid(sil_updates=(1, 4), sil_weight=(0.1, 1.0), sil_capacity=(10_000, 100_000))
    ]
    return [{"sil_batch": 64, **row} for row in out]


def config_id(config: Mapping[str, Any]) -> str:
    """A short, stable name of a setting (its JSON's hash)."""
    text = json.dumps(dict(config), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


@dataclass(frozen=True)
class RunKey:
    """One run of the study: where its record lives and what it runs."""

    stage: str
    variant: str
    arm: str
    seed: int
    config: Mapping[str, Any] = field(default_factory=dict)

    @property
    def path(self) -> str:
        """The record's path under the runs directory."""
        tag = self.arm if not self.config else f"{self.arm}-{config_id(self.config)}"
        return f"{self.stage}/{self.variant}/{tag}/seed{self.seed}.json.gz"


#: The confirmation's arms per family (the oracle only where shortest paths are known).
FAMILY_ARMS = {
    "E1": ARMS,
    "E2": tuple(a for a in ARMS if a != "oracle"),
    "E3": tuple(a for a in ARMS if a != "oracle"),
}


def family_variants(family: str) -> list[Variant]:
    """The confirmation's variants of a family, the tuned one first."""
    return sorted(
        (v for v in VARIANTS.values() if v.family == family), key=lambda v: not v.tuned_here
    )


def tuned_variant(family: str) -> Variant:
    """The variant a family's settings are tuned on."""
    return family_variants(family)[0]


@dataclass(frozen=True)
class Scale:
    """How much of the study to run: the registered grid, or a smoke test of its code."""

    tune_seeds: tuple[int, ...] = TUNE_SEEDS
    confirm_seeds: tuple[int, ...] = CONFIRM_SEEDS
    #: Settings of each grid kept (None: all).
    grid_size: int | None = None

    def cut(self, grid: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The grid, or its first ``grid_size`` settings."""
        return grid if self.grid_size is None else grid[: self.grid_size]


FULL = Scale()
QUICK = Scale(tune_seeds=(1000,), confirm_seeds=(0, 1), grid_size=2)


def tune_a_keys(family: str, scale: Scale = FULL) -> list[RunKey]:
    """Stage A of the shaping grid, SIL's grid and plain, on the family's tuning seeds."""
    v = tuned_variant(family).name
    keys = [RunKey("tune", v, "plain", s) for s in scale.tune_seeds]
    keys += [
        RunKey("tune", v, "tamrm", s, c)
        for c in scale.cut(stage_a_grid())
        for s in scale.tune_seeds
    ]
    keys += [
        RunKey("tune", v, "sil", s, c) for c in scale.cut(sil_grid()) for s in scale.tune_seeds
    ]
    return keys


def tune_b_keys(family: str, best_a: Mapping[str, Any], scale: Scale = FULL) -> list[RunKey]:
    """Stage B of the shaping grid around stage A's best."""
    v = tuned_variant(family).name
    return [
        RunKey("tune", v, "tamrm", s, c)
        for c in scale.cut(stage_b_grid(best_a))
        for s in scale.tune_seeds
    ]


def select(scores: Mapping[str, list[float]], grid: list[dict[str, Any]]) -> dict[str, Any]:
    """The registered rule: the setting with the highest mean AUC over the tuning seeds
    (``scores``: config id -> AUCs); a tie goes to the earlier setting of the grid. Only
    settings with every tuning seed finished take part.

    Raises:
        ValueError: No setting has all its runs.
    """
    best: tuple[float, int] | None = None
    choice: dict[str, Any] | None = None
    for i, config in enumerate(grid):
        values = scores.get(config_id(config))
        if not values:
            continue
        mean = sum(values) / len(values)
        if best is None or mean > best[0]:
            best, choice = (mean, i), config
    if choice is None:
        raise ValueError("no setting of the grid has all its tuning runs")
    return choice


def confirm_keys(
    family: str, shaping: Mapping[str, Any], sil: Mapping[str, Any], scale: Scale = FULL
) -> list[RunKey]:
    """The confirmation: every arm of the family on every variant and fresh seed, with the
    frozen settings (``shaping`` for knn, tamrm and oracle; ``sil`` for sil)."""
    keys = []
    for s in scale.confirm_seeds:
        for v in family_variants(family):
            for arm in FAMILY_ARMS[family]:
                config: Mapping[str, Any] = {}
                if arm in ("knn", "tamrm", "oracle"):
                    config = shaping
                elif arm == "sil":
                    config = sil
                keys.append(RunKey("confirm", v.name, arm, s, config))
    return keys
