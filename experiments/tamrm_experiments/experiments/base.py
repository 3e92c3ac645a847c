"""What every experiment module defines: its setup, budgets, metrics, plot and claims.

The report (``tamrm_experiments.report``) is generic: everything that differs between the
paper's experiments lives in one :class:`ExperimentDef` subclass per experiment, in this
package (``cartpole.py``, ``mountaincar.py``, ``maze.py``, ``maze_modified.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pandas as pd

__all__ = [
    "ARMS",
    "CLEAN_VARIANTS",
    "DQN_COMMON",
    "FIDELITIES",
    "Arm",
    "Budget",
    "Claim",
    "ExperimentDef",
    "Metric",
    "Variant",
    "claim_word",
]

#: ``clean``: Stable-Baselines3 learners and SPEC defaults where the paper is silent;
#: ``authors``: the authors' published code's learners, environments, gating and signs.
FIDELITIES = ("clean", "authors")


@dataclass(frozen=True)
class Variant:
    """One setting of an experiment, run with every arm.

    Attributes:
        name: Directory name of its runs (``clean``, ``authors-fixed``, ...).
        fidelity: ``"clean"`` or ``"authors"``.
        label: Human label.
        settings: What the variant changes (recorded in each run's JSON). For ``clean``:
            ``gate_potential``. For ``authors``: the learner, the task configuration of the
            TAMRM arm (``pool_capacity``, ``k``, ``start_step``, ``alpha``, ``beta``,
            ``gamma``), ``pbrs_beta`` (their PBRS-only line), ``terminal_reward`` (their
            override of the reward of a terminal step), and environment switches.
        budgets: Budgets per profile replacing the experiment's (e.g. a larger episode cap
            for the unwrapped mountain car).
        runnable: False for a variant that only labels earlier runs (``clean-v1``): the
            grid never schedules it.
        plain_from: The variant whose plain runs this one uses instead of its own, when
            the two differ only in shaping settings (signs, ``pbrs_beta``,
            ``gate_potential``, the kNN pool), which the plain arm (alpha = beta = 0) never
            reads: the
            grid runs plain once for both, and the report compares both variants' arms
            with the same plain runs (``configs.plain_key`` checks the declaration).
    """

    name: str
    fidelity: str
    label: str
    settings: dict[str, Any] = field(default_factory=dict)
    budgets: dict[str, Budget] = field(default_factory=dict)
    runnable: bool = True
    plain_from: str | None = None


@dataclass(frozen=True)
class Arm:
    """One arm: which of the two shaping terms is switched on."""

    name: str
    label: str
    knn: bool
    potential: bool
    #: Its name in compact tables (the README's summary).
    short: str = ""


ARMS: dict[str, Arm] = {
    arm.name: arm
    for arm in (
        Arm("plain", "plain (no shaping)", knn=False, potential=False, short="plain"),
        Arm("pbrs", "PBRS only (alpha = 0)", knn=False, potential=True, short="PBRS only"),
        Arm("knn", "kNN only (beta = 0)", knn=True, potential=False, short="kNN only"),
        Arm("tamrm", "TAMRM (kNN + PBRS)", knn=True, potential=True, short="TAMRM"),
    )
}

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
class Claim:
    """One of the paper's claims about an experiment: ``arm`` vs plain on ``metric``.

    ``direction`` is the sign the paper claims for (arm - plain): -1 "fewer steps", +1
    "more steps kept up" / "solved more often". The metric ``solved`` (0/1 per seed) is
    tested with Fisher's exact test, every other with Welch's t-test.
    """

    text: str
    paper: str
    arm: str
    metric: str
    direction: int


@dataclass(frozen=True)
class Metric:
    """A per-run number; ``lower_is_better`` says which direction is an improvement."""

    key: str
    label: str
    lower_is_better: bool
    fmt: str = "{:,.0f}"


@dataclass(frozen=True)
class ExperimentDef:
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
        budgets: This experiment's budget in each profile (``full``, ``paper``, ``quick``).
        switch_after: Modified maze: episodes after which the start moves and the
            shaping arms switch to a fresh task (pool).
        score_from_info: Send ``info["episode_score"]`` as the episode score.
        variants: The settings it is run in (see :class:`Variant`).
    """

    name: str
    title: str
    env: str
    algo: str
    algo_kwargs: dict[str, Any]
    tamrm: dict[str, Any]
    episodes: int
    max_episode_steps: int
    budgets: dict[str, Budget] = field(default_factory=dict)
    switch_after: int | None = None
    score_from_info: bool = False
    variants: tuple[Variant, ...] = ()

    def variant(self, name: str) -> Variant:
        """The variant called ``name``."""
        for v in self.variants:
            if v.name == name:
                return v
        raise KeyError(f"{self.name} has no variant {name!r}")

    def budget(self, profile: str, variant: str) -> Budget:
        """The budget of ``variant`` in ``profile``."""
        return self.variant(variant).budgets.get(profile) or self.budgets[profile]

    # -- what the report needs; subclasses override ------------------------------------

    #: The metrics of the experiment's table (the headline is ``headline``).
    metrics: ClassVar[tuple[Metric, ...]] = (
        Metric("total_steps", "total steps", True),
        Metric("last20", "mean steps per episode, last 20 episodes", True, "{:,.1f}"),
    )
    #: The key of the paper's headline metric.
    headline: ClassVar[str] = "total_steps"
    #: The paper's number (or words) per arm.
    paper: ClassVar[dict[str, str]] = {}
    #: The paper's claims about this experiment, checked in the report's claims table.
    claims: ClassVar[tuple[Claim, ...]] = ()
    #: Plot: episodes of the trailing mean.
    plot_window: ClassVar[int] = 10

    @property
    def short(self) -> str:
        """The title without its parenthesis ("Cart pole")."""
        return self.title.split(" (")[0]

    def extra_metrics(self, df: pd.DataFrame, meta: dict[str, Any], unfinished: float) -> dict:
        """Metrics beyond the common ones (``total_steps``, ``last20``, ``episodes``).

        ``unfinished`` is the step count of an unfinished last episode of a run stopped by
        its step cap (already added to ``total_steps``).
        """
        return {}

    def status_column(self) -> str:
        """Header of the per-arm status column of the table."""
        return "seeds stopped by the step cap"

    def status_cell(self, metrics: list[dict[str, float]], censored: int) -> str:
        """The status cell of one arm."""
        return f"{censored}/{len(metrics)}"

    # -- plot --------------------------------------------------------------------------

    #: Plot the steps per episode on a log axis (geometric mean over seeds).
    plot_log: ClassVar[bool] = True

    def plot_ylabel(self) -> str:
        """The y label of the learning-curve plot."""
        return f"steps per episode (mean of last {self.plot_window})"

    def decorate(self, ax: Any) -> None:
        """Add experiment-specific lines to the plot (e.g. the solved threshold)."""


def mean_or_nan(x: np.ndarray) -> float:
    """Mean of ``x``, ``nan`` if empty."""
    return float(x.mean()) if len(x) else math.nan


def claim_word(better: bool | None) -> str:
    """Our verdict on a claim that TAMRM is better than plain, in words."""
    return {
        True: "reproduced (TAMRM significantly better than plain)",
        False: "contradicted (TAMRM significantly worse than plain)",
        None: "not reproduced (no difference detectable at 95% with these seeds)",
    }[better]


#: The clean variants every experiment has: SPEC defaults, the potential term ungated (as
#: the first report ran) and gated to the kNN window (SPEC v1.1 ``gate_potential``).
CLEAN_VARIANTS: tuple[Variant, ...] = (
    Variant("clean", "clean", "clean (SB3, gate_potential off)", {"gate_potential": False}),
    # Gating changes only beta F, which is 0 in the plain arm: plain runs once, as clean's.
    Variant(
        "clean-gated",
        "clean",
        "clean (SB3, gate_potential on)",
        {"gate_potential": True},
        plain_from="clean",
    ),
    # The first report's runs (docs/reproduction/runs-v1/): SB3 learners,
    # the potential ungated, the reduced ``full`` budgets, the maze's DQN on the (x, y)
    # cell. Read by ``report --previous``; never run again.
    Variant(
        "clean-v1",
        "clean",
        "clean, first report (SB3, gate off, reduced budgets)",
        {"gate_potential": False},
        runnable=False,
    ),
)
