"""A trial's numbers: each run's learning curve and metrics, each arm against ``plain``.

Everything is computed on the environment's own episodic return (recorded by the
``Monitor`` below the shaping wrapper), never on shaped rewards.

- **Curve**: at 100 evenly spaced timesteps x_g = g·T/100, the mean return of the
  episodes that ended in (x_{g-1}, x_g]; where none ended, the previous point's value;
  before the first episode ends, that episode's return.
- **AUC** (the primary metric): the mean of the curve's 100 points, the area under the
  curve divided by T: in units of return, higher is better.
- **Final return**: the mean return of the episodes that ended in the last 10 % of the
  timesteps (the curve's last point if none did).
- **Timesteps to threshold** (with ``--threshold R``): the first episode end at which the
  mean return of the last 10 episodes reaches R; a run that never does is *censored* at
  its budget, T, which is counted as its value (so its difference is a lower bound).

Each arm is compared with ``plain`` seed by seed (paired): the mean paired difference
with a bootstrap 95 % interval, the two-sided Wilcoxon signed-rank p-value, and Holm's
correction over the arms compared (``null``, the harness check, is not one of them). The
verdict on the AUC is one of:

- *helps* / *hurts*: Holm-adjusted p < 0.05, by the sign of the mean difference;
- *no difference large enough to matter*: the signed-rank equivalence test (two one-sided
  tests) puts the difference inside ±margin at the 5 % level;
- *not enough seeds to tell*: neither; with the number of seeds that would resolve it at
  the observed spread.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from tamrm.trial.settings import Margin
from tamrm.trial.stats import (
    Interval,
    bootstrap_interval,
    holm,
    seeds_needed,
    t_interval,
    wilcoxon_equivalence_p,
    wilcoxon_p,
)

__all__ = [
    "CURVE_POINTS",
    "LEVEL",
    "Comparison",
    "RunMetrics",
    "compare",
    "curve",
    "null_identity",
    "run_metrics",
]

#: Points of a learning curve.
CURVE_POINTS = 100
#: The significance level of every test.
LEVEL = 0.05
#: The share of the budget whose episodes make the final return.
_FINAL_SHARE = 0.1
#: Episodes averaged for the threshold crossing.
_THRESHOLD_WINDOW = 10


def curve(
    record: Mapping[str, Any], timesteps: int, points: int = CURVE_POINTS
) -> npt.NDArray[np.float64]:
    """The run's learning curve at ``points`` evenly spaced timesteps (see the module)."""
    returns = np.asarray(record["episodes"]["return"], dtype=np.float64)
    ends = np.asarray(record["episodes"]["timestep"], dtype=np.float64)
    out = np.full(points, np.nan)
    if returns.size == 0:
        return out
    edges = np.linspace(0.0, float(timesteps), points + 1)
    # Episode i ends in bin b when edges[b] < ends[i] <= edges[b + 1].
    bins = np.clip(np.searchsorted(edges, ends, side="left") - 1, 0, points - 1)
    sums = np.bincount(bins, weights=returns, minlength=points)
    counts = np.bincount(bins, minlength=points)
    value = float(returns[0])
    for b in range(points):
        if counts[b]:
            value = float(sums[b] / counts[b])
        out[b] = value
    return out


@dataclass(frozen=True)
class RunMetrics:
    """One run's metrics (``nan`` where it has no episode)."""

    auc: float
    final: float
    episodes: int
    to_threshold: float | None = None
    censored: bool = False


def run_metrics(record: Mapping[str, Any], timesteps: int, threshold: float | None) -> RunMetrics:
    """The metrics of one run record (see the module)."""
    returns = np.asarray(record["episodes"]["return"], dtype=np.float64)
    ends = np.asarray(record["episodes"]["timestep"], dtype=np.float64)
    points = curve(record, timesteps)
    if returns.size == 0:
        return RunMetrics(
            math.nan,
            math.nan,
            0,
            None if threshold is None else float(timesteps),
            threshold is not None,
        )
    late = returns[ends > (1 - _FINAL_SHARE) * timesteps]
    final = float(late.mean()) if late.size else float(points[-1])
    to_threshold: float | None = None
    censored = False
    if threshold is not None:
        c = np.cumsum(np.insert(returns, 0, 0.0))
        idx = np.arange(1, returns.size + 1)
        lo = np.maximum(0, idx - _THRESHOLD_WINDOW)
        means = (c[idx] - c[lo]) / (idx - lo)
        hits = np.flatnonzero(means >= threshold)
        if hits.size:
            to_threshold = float(ends[hits[0]])
        else:
            to_threshold, censored = float(timesteps), True
    return RunMetrics(float(points.mean()), final, int(returns.size), to_threshold, censored)


@dataclass
class Test:
    """One metric of one arm against ``plain``, over the paired seeds."""

    metric: str
    n: int
    difference: Interval
    p: float
    p_holm: float = math.nan
    better: str = "higher"
    differences: list[float] = field(default_factory=list)


@dataclass
class Comparison:
    """One arm against ``plain``: the paired tests and the verdict on the AUC."""

    arm: str
    seeds: list[int]
    tests: dict[str, Test]
    margin: float
    equivalence_p: float
    verdict: str = ""
    #: The verdict as a sentence, and what it rests on.
    headline: str = ""
    sentence: str = ""
    seeds_needed: int | None = None
    censored: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """A JSON-able form for ``summary.json``."""
        out = asdict(self)
        for test in out["tests"].values():
            test["difference"] = asdict(self.tests[test["metric"]].difference)
        return out


def _paired_test(metric: str, diffs: Sequence[float], better: str) -> Test:
    return Test(
        metric,
        len(diffs),
        bootstrap_interval(diffs),
        wilcoxon_p(diffs),
        better=better,
        differences=list(diffs),
    )


def compare(
    metrics: Mapping[tuple[str, int], RunMetrics],
    arms: Sequence[str],
    margin: Margin,
    threshold: float | None,
) -> list[Comparison]:
    """Compare every arm but ``plain`` and ``null`` with ``plain``, paired by seed.

    Holm's correction is over these arms, per metric; the verdict is on the AUC.
    """
    plain = {seed: m for (arm, seed), m in metrics.items() if arm == "plain"}
    plain_auc = t_interval([m.auc for m in plain.values()]).mean
    margin_abs = margin.of(plain_auc) if not math.isnan(plain_auc) else math.nan
    out: list[Comparison] = []
    for arm in arms:
        if arm in ("plain", "null"):
            continue
        seeds = sorted(s for (a, s) in metrics if a == arm and s in plain)
        pairs = [(metrics[(arm, s)], plain[s]) for s in seeds]
        auc = [a.auc - p.auc for a, p in pairs]
        tests = {
            "auc": _paired_test("auc", auc, "higher"),
            "final": _paired_test("final", [a.final - p.final for a, p in pairs], "higher"),
        }
        censored: dict[str, int] = {}
        if threshold is not None:
            diffs = [float(a.to_threshold or 0) - float(p.to_threshold or 0) for a, p in pairs]
            tests["to_threshold"] = _paired_test("to_threshold", diffs, "lower")
            censored = {
                arm: sum(a.censored for a, _ in pairs),
                "plain": sum(p.censored for _, p in pairs),
            }
        out.append(
            Comparison(
                arm,
                seeds,
                tests,
                margin_abs,
                wilcoxon_equivalence_p(auc, margin_abs),
                censored=censored,
            )
        )
    for metric in ("auc", "final", "to_threshold"):
        family = [c.tests[metric] for c in out if metric in c.tests]
        for test, adjusted in zip(family, holm([t.p for t in family]), strict=True):
            test.p_holm = adjusted
    for comparison in out:
        _verdict(comparison, family_size=len(out))
    return out


def _verdict(c: Comparison, family_size: int) -> None:
    """Set the verdict on the AUC, its sentence and the seeds that would resolve it."""
    test = c.tests["auc"]
    d = test.difference
    n = test.n
    diffs_interval = (
        f"{d.mean:+.4g} (95 % CI {d.low:+.4g} to {d.high:+.4g})" if n >= 2 else f"{d.mean:+.4g}"
    )
    if n >= 2 and test.p_holm < LEVEL and d.mean != 0:
        c.verdict = "helps" if d.mean > 0 else "hurts"
        c.headline = f"{c.arm} {c.verdict}."
        c.sentence = (
            f"Its AUC differs from plain's by {diffs_interval} over {n} paired seeds, "
            f"Wilcoxon p = {test.p_holm:.3g} after Holm's correction."
        )
        return
    if n >= 2 and c.equivalence_p < LEVEL:
        c.verdict = "no difference"
        c.headline = f"{c.arm} makes no difference large enough to matter."
        c.sentence = (
            f"The AUC difference {diffs_interval} lies within ±{c.margin:.4g} "
            f"(equivalence p = {c.equivalence_p:.3g})."
        )
        return
    c.verdict = "not enough seeds"
    # At the level the smallest of Holm's p-values must reach (and never fewer seeds
    # than the exact signed-rank test needs to reach it at all).
    c.seeds_needed = seeds_needed(
        test.differences,
        c.margin if not math.isnan(c.margin) else None,
        alpha=LEVEL / max(1, family_size),
    )
    c.headline = f"{c.arm}: not enough seeds to tell."
    if n < 2:
        c.sentence = f"{n} paired seed{'s' * (n != 1)}."
        return
    more = (
        f" About {c.seeds_needed} paired seeds would resolve it at the observed spread."
        if c.seeds_needed is not None
        else ""
    )
    c.sentence = (
        f"The AUC difference {diffs_interval} over {n} paired seeds is neither significant "
        f"(p = {test.p_holm:.3g} after Holm) nor shown to lie within ±{c.margin:.4g} "
        f"(equivalence p = {c.equivalence_p:.3g}).{more}"
    )


def null_identity(records: Mapping[tuple[str, int], Mapping[str, Any]]) -> dict[int, bool]:
    """Tell, per seed with both runs, whether ``null`` learned bit for bit what ``plain`` did.

    Bit for bit: the same episodes, returns and final parameters.
    """
    out: dict[int, bool] = {}
    for (arm, seed), null in records.items():
        plain = records.get(("plain", seed))
        if arm != "null" or plain is None:
            continue
        same = all(
            null["episodes"][k] == plain["episodes"][k] for k in ("return", "length", "timestep")
        )
        out[seed] = same and null["policy_sha256"] == plain["policy_sha256"]
    return out
