"""Statistics of the report: t-intervals over seeds and per-run metrics."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

__all__ = [
    "Interval",
    "first_solved_episode",
    "fisher_p",
    "fmt",
    "fmt_interval",
    "holm",
    "rolling_mean",
    "t_interval",
    "welch_interval",
    "welch_p",
]


@dataclass(frozen=True)
class Interval:
    """A mean with a two-sided confidence interval (``nan`` bounds when n < 2)."""

    mean: float
    low: float
    high: float
    n: int

    @property
    def half_width(self) -> float:
        """Half the interval's width."""
        return (self.high - self.low) / 2

    def excludes(self, value: float) -> bool:
        """Whether the interval lies entirely on one side of ``value``."""
        if math.isnan(self.low) or math.isnan(self.high):
            return False
        return value < self.low or value > self.high


def t_interval(values: Sequence[float], confidence: float = 0.95) -> Interval:
    """Student-t confidence interval of the mean of ``values`` (independent seeds)."""
    x = np.asarray(values, dtype=np.float64)
    x = x[~np.isnan(x)]
    n = int(x.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n == 1:
        return Interval(mean, math.nan, math.nan, 1)
    se = float(x.std(ddof=1)) / math.sqrt(n)
    if se == 0.0:
        return Interval(mean, mean, mean, n)
    h = float(sps.t.ppf((1 + confidence) / 2, n - 1)) * se
    return Interval(mean, mean - h, mean + h, n)


def welch_interval(a: Sequence[float], b: Sequence[float], confidence: float = 0.95) -> Interval:
    """Welch-t confidence interval of ``mean(a) - mean(b)`` (unequal variances)."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    x = x[~np.isnan(x)]
    y = y[~np.isnan(y)]
    n = min(x.size, y.size)
    if x.size == 0 or y.size == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    diff = float(x.mean() - y.mean())
    if x.size < 2 or y.size < 2:
        return Interval(diff, math.nan, math.nan, n)
    vx = float(x.var(ddof=1)) / x.size
    vy = float(y.var(ddof=1)) / y.size
    se = math.sqrt(vx + vy)
    if se == 0.0:
        return Interval(diff, diff, diff, n)
    df = (vx + vy) ** 2 / (vx**2 / (x.size - 1) + vy**2 / (y.size - 1))
    h = float(sps.t.ppf((1 + confidence) / 2, df)) * se
    return Interval(diff, diff - h, diff + h, n)


def rolling_mean(values: Sequence[float], window: int) -> np.ndarray:
    """Trailing mean over up to ``window`` values (shorter at the start)."""
    x = np.asarray(values, dtype=np.float64)
    if x.size == 0:
        return x
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(0, idx - window)
    return (c[idx] - c[lo]) / (idx - lo)


def first_solved_episode(
    steps: Sequence[float], threshold: float = 195.0, window: int = 100
) -> int | None:
    """First episode (1-based) at which the mean of the last ``window`` episodes reaches
    ``threshold``; ``None`` if never. Needs ``window`` full episodes."""
    x = np.asarray(steps, dtype=np.float64)
    if x.size < window:
        return None
    c = np.cumsum(np.insert(x, 0, 0.0))
    means = (c[window:] - c[:-window]) / window
    hits = np.flatnonzero(means >= threshold)
    if hits.size == 0:
        return None
    return int(hits[0]) + window


def welch_p(a: Sequence[float], b: Sequence[float]) -> float:
    """Two-sided p-value of Welch's t-test of equal means (``nan`` if undefined)."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    x = x[~np.isnan(x)]
    y = y[~np.isnan(y)]
    if x.size < 2 or y.size < 2:
        return math.nan
    if x.var(ddof=1) == 0 and y.var(ddof=1) == 0:
        return 1.0 if x.mean() == y.mean() else 0.0
    return float(sps.ttest_ind(x, y, equal_var=False).pvalue)


def fisher_p(successes_a: int, n_a: int, successes_b: int, n_b: int) -> float:
    """Two-sided p-value of Fisher's exact test of equal success rates."""
    if n_a == 0 or n_b == 0:
        return math.nan
    table = [[successes_a, n_a - successes_a], [successes_b, n_b - successes_b]]
    return float(sps.fisher_exact(table).pvalue)


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (same order; ``nan`` entries stay ``nan`` and do
    not count in the family)."""
    p = np.asarray(pvalues, dtype=np.float64)
    out = np.full(p.size, math.nan)
    idx = np.flatnonzero(~np.isnan(p))
    m = idx.size
    running = 0.0
    for rank, i in enumerate(idx[np.argsort(p[idx], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out.tolist()


def fmt(value: float | None, pattern: str) -> str:
    """``value`` formatted with ``pattern`` (a ``str.format`` one), ``-`` if undefined."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return pattern.format(value)


def fmt_interval(iv: Interval, pattern: str) -> str:
    """``mean [low, high]``, ``mean (n=1)`` without bounds, ``-`` without values."""
    if iv.n == 0:
        return "-"
    if iv.n == 1 or math.isnan(iv.low):
        return f"{fmt(iv.mean, pattern)} (n=1)"
    return f"{fmt(iv.mean, pattern)} [{fmt(iv.low, pattern)}, {fmt(iv.high, pattern)}]"
