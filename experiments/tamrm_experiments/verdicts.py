"""Verdicts: per-run metrics, each arm against plain, the paper's claims and the pilot.

Everything the report and the README's summary conclude is computed here from the loaded
runs (:mod:`tamrm_experiments.load`); rendering is :mod:`tamrm_experiments.markdown`'s.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tamrm.trial.stats import (
    Interval,
    fisher_p,
    fmt,
    fmt_interval,
    holm,
    t_interval,
    welch_interval,
    welch_p,
)

from tamrm_experiments.configs import EXPERIMENTS
from tamrm_experiments.envs import random_policy_steps
from tamrm_experiments.experiments.base import Claim, Metric
from tamrm_experiments.load import Group, Key, Run, group_runs, load_runs, requested_runs, wanted

__all__ = [
    "CENSORABLE",
    "Analysis",
    "ClaimRow",
    "Comparison",
    "Pilot",
    "adjust",
    "analyse",
    "censoring_caveat",
    "claim_rows",
    "compare",
    "distinct_tests",
    "plain_learns",
    "run_metrics",
]


def run_metrics(run: Run) -> dict[str, float]:
    """The metrics of one run (``nan`` where undefined)."""
    df = run.df
    steps = df["steps"].to_numpy(dtype=np.float64)
    out: dict[str, float] = {
        "episodes": float(len(df)),
        "total_steps": float(steps.sum()),
        "last20": float(steps[-20:].mean()) if len(steps) else math.nan,
        "successes": float(df["success"].sum()) if len(df) else 0.0,
    }
    # A run stopped by its step cap has an unfinished last episode: its steps count in the
    # totals (which are then lower bounds), in the phase it belongs to.
    unfinished = max(0.0, float(run.meta.get("total_steps", 0)) - out["total_steps"])
    out["total_steps"] += unfinished
    out.update(EXPERIMENTS[run.experiment].extra_metrics(df, run.meta, unfinished))
    return out


@dataclass
class Comparison:
    """Arm minus plain on one metric."""

    arm: str
    metric: Metric
    diff: Interval
    better: bool | None = None  # True better, False worse, None no detectable difference
    text: str = field(default="")


def compare(
    metric: Metric, arm_values: list[float], plain_values: list[float], arm: str
) -> Comparison:
    """Welch interval of (arm - plain) and a verdict in words."""
    diff = welch_interval(arm_values, plain_values)
    if diff.n < 2 or not diff.excludes(0.0):
        better = None
    else:
        better = (diff.high < 0) if metric.lower_is_better else (diff.low > 0)
    rel = ""
    base = float(np.nanmean(plain_values)) if len(plain_values) else math.nan
    if base and not math.isnan(base) and not math.isnan(diff.mean):
        rel = f" ({diff.mean / base:+.0%} of plain)"
    ci = (
        f"[{fmt(diff.low, metric.fmt)}, {fmt(diff.high, metric.fmt)}]"
        if not math.isnan(diff.low)
        else "[n/a]"
    )
    word = {True: "better", False: "worse", None: "no detectable difference"}[better]
    text = f"{fmt(diff.mean, metric.fmt)}{rel}, 95% CI {ci}: {word}"
    return Comparison(arm, metric, diff, better, text)


#: Totals that a run stopped by its step cap only bounds from below.
CENSORABLE = ("total_steps", "phase1_steps", "phase2_steps")


def censoring_caveat(comp: Comparison, arm_censored: bool, plain_censored: bool) -> Comparison:
    """Keep a verdict only if censoring (totals that are lower bounds) cannot reverse it."""
    # A censored total understates the true one. If only plain is censored, "arm better"
    # stands (plain's true total is even larger); if only the arm is, "arm worse" stands.
    safe = (plain_censored and not arm_censored and comp.better is True) or (
        arm_censored and not plain_censored and comp.better is False
    )
    if safe:
        comp.text += " (some totals are lower bounds; they can only widen this gap)"
    elif comp.better is None:
        comp.text += " (some totals are lower bounds)"
    else:
        comp.better = None
        comp.text += (
            " - but some totals are lower bounds (runs stopped by the step cap), so this "
            "is counted as undecided"
        )
    return comp


@dataclass
class ClaimRow:
    """One claim measured in one variant."""

    exp_name: str
    variant: str
    claim: Claim
    arm_values: list[float]
    plain_values: list[float]
    planned: int  # seeds per arm asked for (by some invocation)
    diff: Interval = field(default_factory=lambda: Interval(math.nan, math.nan, math.nan, 0))
    p: float = math.nan
    p_holm: float = math.nan
    censored: bool = False

    @property
    def test_key(self) -> tuple[Any, ...]:
        """What the test reads: its metric and its two samples."""
        return (self.claim.metric, tuple(self.arm_values), tuple(self.plain_values))

    @property
    def complete(self) -> bool:
        """Every requested seed of both arms is done."""
        n = min(len(self.arm_values), len(self.plain_values))
        return n >= self.planned > 0

    def measure(self) -> None:
        """The interval of (arm - plain) and the unadjusted p-value."""
        self.diff = welch_interval(self.arm_values, self.plain_values)
        if self.claim.metric == "solved":
            k_a, k_p = int(sum(self.arm_values)), int(sum(self.plain_values))
            self.p = fisher_p(k_a, len(self.arm_values), k_p, len(self.plain_values))
        else:
            self.p = welch_p(self.arm_values, self.plain_values)

    def judge(self) -> tuple[str, str]:
        """(word, kind): the verdict's word and which case of it, one of ``too-few``,
        ``censored``, ``holds``, ``opposite``, ``pending``, ``claimed-way``,
        ``other-way`` (the last two: unadjusted p < 0.05, not after Holm) and ``none``."""
        n_a, n_p = len(self.arm_values), len(self.plain_values)
        if n_a < 2 or n_p < 2:
            return "cannot be decided yet", "too-few"
        sig = not math.isnan(self.p_holm) and self.p_holm < 0.05
        if sig and self.sign == self.claim.direction:
            if self.censored and self.claim.direction == -1:
                return "cannot be decided yet", "censored"
            return "holds", "holds"
        if sig:
            return "does not hold", "opposite"
        if not self.complete:
            return "cannot be decided yet", "pending"
        if not math.isnan(self.p) and self.p < 0.05:
            way = "claimed-way" if self.sign == self.claim.direction else "other-way"
            return "does not hold", way
        return "does not hold", "none"

    @property
    def sign(self) -> int:
        """The sign of the estimated (arm - plain): -1, 0 or +1."""
        return 0 if math.isnan(self.diff.mean) else (1 if self.diff.mean > 0 else -1)

    @property
    def seeds(self) -> int:
        """Seeds done in both arms."""
        return min(len(self.arm_values), len(self.plain_values))

    def verdict(self) -> tuple[str, str]:
        """(word, why): ``holds``, ``does not hold`` or ``cannot be decided yet``."""
        word, kind = self.judge()
        n = self.seeds
        if kind == "too-few":
            n_a, n_p = len(self.arm_values), len(self.plain_values)
            return word, f"{n_a} and {n_p} of {self.planned} seeds done"
        if kind == "censored":
            return word, "significant, but some totals are lower bounds"
        if kind == "holds":
            return word, f"Holm-adjusted p = {self.p_holm:.3g}"
        if kind == "opposite":
            return word, (
                f"significant in the opposite direction (Holm-adjusted p = {self.p_holm:.3g})"
            )
        hint = ""
        if not math.isnan(self.p) and self.p < 0.05:
            hint = f"; unadjusted p = {self.p:.2g}, " + (
                "in the claimed direction" if self.sign == self.claim.direction else "the other way"
            )
        if kind == "pending":
            return word, (
                f"no significant difference with {n} of {self.planned} seeds "
                "done (Holm-adjusted p = "
                f"{self.p_holm:.2g}{hint})"
            )
        if kind == "claimed-way":
            # A large but variable effect: say so rather than call it small.
            return word, (
                f"no significant difference at {n} seeds after Holm's correction "
                f"(Holm-adjusted p = {self.p_holm:.2g}{hint}): the estimate points the claimed "
                "way, but the seeds vary too much for it to survive the correction for the "
                "table's tests"
            )
        return word, (
            f"no significant difference at {n} seeds (Holm-adjusted p = "
            f"{self.p_holm:.2g}{hint}): any effect in the claimed direction is smaller than "
            "these seeds resolve"
        )

    def short_verdict(self) -> str:
        """The verdict in a few words, for the README's summary."""
        word, kind = self.judge()
        why = {
            "too-few": f"{self.seeds} of {self.planned} seeds done",
            "censored": "significant, but some totals are lower bounds",
            "holds": "",
            "opposite": "significant the other way",
            "pending": f"{self.seeds} of {self.planned} seeds done",
            "claimed-way": "the claimed way, not significant after Holm",
            "other-way": "the other way, not significant after Holm",
            "none": "no significant difference",
        }[kind]
        return f"**{word}**" + (f": {why}" if why else "")

    def cell(self) -> str:
        """The measured cell: both arms, the difference, the test."""
        pattern = "{:,.2f}" if self.claim.metric == "solved" else "{:,.1f}"
        if self.claim.metric == "solved":
            parts = [
                f"{self.claim.arm} {int(sum(self.arm_values))}/{len(self.arm_values)}, "
                f"plain {int(sum(self.plain_values))}/{len(self.plain_values)} seeds solved"
            ]
        else:
            a = fmt_interval(t_interval(self.arm_values), pattern)
            p = fmt_interval(t_interval(self.plain_values), pattern)
            parts = [f"{self.claim.arm} {a}, plain {p}"]
        if self.claim.metric == "solved":
            if not math.isnan(self.p):
                parts.append(f"Fisher p = {self.p:.2g}, Holm {self.p_holm:.2g}")
        elif not math.isnan(self.diff.low):
            parts.append(
                f"difference {fmt(self.diff.mean, pattern)} [{fmt(self.diff.low, pattern)}, "
                f"{fmt(self.diff.high, pattern)}], p = {self.p:.2g}, Holm {self.p_holm:.2g}"
            )
        prefix = "≥ " if self.censored and self.claim.metric in CENSORABLE else ""
        return prefix + "; ".join(parts)


def claim_rows(groups: dict[Group, list[Run]], requested: list[Key]) -> list[ClaimRow]:
    """Every claim of every experiment measured in each of its groups whose claimed arm
    was run or asked for, Holm-adjusted together (:func:`adjust`)."""
    rows = []
    for (exp_name, variant), runs in groups.items():
        exp = EXPERIMENTS[exp_name]
        for claim in exp.claims:
            by_arm = {arm: [r for r in runs if r.arm == arm] for arm in (claim.arm, "plain")}
            planned = min(
                len(wanted(requested, exp_name, variant, arm)) for arm in (claim.arm, "plain")
            )
            asked = {
                arm for arm in (claim.arm, "plain") if wanted(requested, exp_name, variant, arm)
            }
            if not by_arm[claim.arm] and claim.arm not in asked:
                continue  # this arm is not part of the grid asked for
            done = min(len(by_arm[claim.arm]), len(by_arm["plain"]))
            row = ClaimRow(
                exp_name,
                variant,
                claim,
                [run_metrics(r)[claim.metric] for r in by_arm[claim.arm]],
                [run_metrics(r)[claim.metric] for r in by_arm["plain"]],
                max(planned, done),
                censored=any(r.meta.get("censored") for rs in by_arm.values() for r in rs),
            )
            row.measure()
            rows.append(row)
    adjust(rows)
    return rows


def adjust(rows: list[ClaimRow]) -> None:
    """Holm-adjust the rows' p-values together, each distinct test once: rows whose two
    samples are equal value by value (e.g. the authors' maze PBRS-only arm, which reads
    neither the pool nor k, so pool 3 and pool 10 run identically) are one hypothesis
    tested once, and share its adjusted p-value."""
    slot: dict[tuple[Any, ...], int] = {}
    for row in rows:
        slot.setdefault(row.test_key, len(slot))
    p_of = {slot[row.test_key]: row.p for row in rows}  # equal samples, equal p
    adjusted = holm([p_of[i] for i in range(len(slot))])
    for row in rows:
        row.p_holm = adjusted[slot[row.test_key]]


def distinct_tests(rows: list[ClaimRow]) -> int:
    """How many distinct tests (see :func:`adjust`) with a p-value the rows hold."""
    return len({row.test_key for row in rows if not math.isnan(row.p)})


@dataclass(frozen=True)
class Pilot:
    """Whether a variant's plain learner learns: its first and last 20 episodes (mean steps
    per episode, t-intervals over seeds), a random policy's mean, and the verdict."""

    first: Interval
    last: Interval
    random_policy: float
    verdict: str


@functools.cache
def _random_policy(exp_name: str, max_steps: int, after_switch: bool) -> float:
    """:func:`random_policy_steps`, once per report for each experiment and cap."""
    return random_policy_steps(exp_name, max_steps, after_switch)


def plain_learns(exp_name: str, plain: list[Run]) -> Pilot:
    """The pilot of ``plain`` (runs of at least 40 episodes): ``yes`` if the last 20
    episodes are detectably better than the first 20 or than a random policy, else ``not
    detectably`` (``n=1`` for a single seed, ``-`` without such runs)."""
    plain = [r for r in plain if len(r.df) >= 40]
    first = t_interval([float(r.df["steps"].head(20).mean()) for r in plain])
    last = t_interval([float(r.df["steps"].tail(20).mean()) for r in plain])
    if not plain:
        return Pilot(first, last, math.nan, "-")
    budget = plain[0].budget
    random_policy = _random_policy(
        exp_name, int(budget["max_episode_steps"]), budget.get("switch_after") is not None
    )
    if math.isnan(last.low):
        return Pilot(first, last, random_policy, "n=1")
    if EXPERIMENTS[exp_name].headline == "mean_steps":  # more steps kept up is better
        better = last.low > first.high or last.low > random_policy
    else:
        better = last.high < first.low or last.high < random_policy
    return Pilot(first, last, random_policy, "yes" if better else "not detectably")


@dataclass
class Analysis:
    """Everything the report and the README's summary compute from the runs."""

    runs_dir: Path
    current: list[Run]  # the runs of ``runs_dir``
    earlier: list[Run]  # the first report's runs, as variant ``clean-v1``
    requested: list[Key]
    groups: dict[Group, list[Run]]
    rows: list[ClaimRow]

    @property
    def runs(self) -> list[Run]:
        """Current and earlier runs."""
        return self.current + self.earlier

    @property
    def progress(self) -> tuple[int, int]:
        """(finished, requested) runs of the current grid."""
        asked = set(self.requested)
        done = sum(1 for r in self.current if r.key in asked)
        return done, len(self.requested) - len(self.earlier)


def analyse(runs_dir: Path, previous: Path | None = None) -> Analysis:
    """Load the runs (and the first report's, ``previous``: runs without a variant, shown
    as the ``clean-v1`` variant, complete as they stand) and measure every claim."""
    current = load_runs(runs_dir)
    earlier = []
    if previous is not None and previous.is_dir():
        for r in load_runs(previous):
            if "variant" not in r.meta["spec"]:
                r.variant = "clean-v1"
                earlier.append(r)
    requested = requested_runs(runs_dir) or [r.key for r in current]
    requested += [r.key for r in earlier]
    groups = group_runs(current + earlier, requested)
    rows = claim_rows(groups, requested) if current or earlier else []
    return Analysis(runs_dir, current, earlier, requested, groups, rows)
