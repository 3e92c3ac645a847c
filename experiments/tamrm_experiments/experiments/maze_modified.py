"""The modified maze (paper §V-C, Fig. 9-10): the start moves mid-run, every arm goes on
with a fresh pool."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from tamrm_experiments.experiments.base import (
    CLEAN_VARIANTS,
    Budget,
    Claim,
    ExperimentDef,
    Metric,
    mean_or_nan,
)
from tamrm_experiments.experiments.maze import AUTHORS_BUDGETS, MAZE_SETUP, authors_variants

__all__ = ["MAZE_MODIFIED", "MazeModified"]


class MazeModified(ExperimentDef):
    """The modified maze: fewer steps after the switch is better."""

    metrics: ClassVar[tuple[Metric, ...]] = (
        Metric("phase2_steps", "total steps after the switch", True),
        Metric("phase1_steps", "total steps before the switch", True),
        Metric("phase2_last10", "mean steps per episode, last 10 episodes", True, "{:,.1f}"),
    )
    headline: ClassVar[str] = "phase2_steps"
    paper: ClassVar[dict[str, str]] = {
        "plain": "Fig. 10: slower to adapt than TAMRM (no number given)",
        "pbrs": "not shown",
        "knn": "not run",
        "tamrm": "Fig. 10: adapts faster (no number given)",
    }
    claims: ClassVar[tuple[Claim, ...]] = (
        Claim(
            "After the start moves, TAMRM (fresh pool) needs fewer steps than plain",
            "Fig. 10: TAMRM adapts faster (no number given)",
            "tamrm",
            "phase2_steps",
            -1,
        ),
    )

    def extra_metrics(self, df: pd.DataFrame, meta: dict[str, Any], unfinished: float) -> dict:
        switch = meta["spec"]["budget"].get("switch_after") or 0
        phase2 = df[df["episode"] > switch]["steps"].to_numpy(dtype=np.float64)
        out = {
            "phase1_steps": float(df[df["episode"] <= switch]["steps"].sum()),
            "phase2_steps": float(phase2.sum()),
            "phase2_last10": mean_or_nan(phase2[-10:]),
        }
        # The unfinished last episode of a run stopped by its step cap belongs to the
        # phase it was in.
        out["phase2_steps" if len(df) >= switch else "phase1_steps"] += unfinished
        return out


MAZE_MODIFIED = MazeModified(
    name="maze_modified",
    title="Modified maze (DQN, the start moves mid-run)",
    **MAZE_SETUP,
    switch_after=100,
    budgets={
        # Half the paper's budget: the start moves after episode 50 (paper: 100).
        "full": Budget(
            episodes=100, max_episode_steps=10_000, max_total_steps=300_000, switch_after=50
        ),
        "paper": Budget(
            episodes=200, max_episode_steps=10_000, max_total_steps=2_000_000, switch_after=100
        ),
        "quick": Budget(episodes=6, max_episode_steps=200, max_total_steps=1_500, switch_after=3),
    },
    # The authors' variants are their maze's (their code has no modified maze): the same
    # learner, shaping, overrides and budgets, the start moved halfway (after episode 100
    # of 200) and a fresh pool from then on, as in the clean variants.
    variants=(
        *CLEAN_VARIANTS,
        *authors_variants(
            {
                name: replace(budget, switch_after=budget.episodes // 2)
                for name, budget in AUTHORS_BUDGETS.items()
            }
        ),
    ),
)
