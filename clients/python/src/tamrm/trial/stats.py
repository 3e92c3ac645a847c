"""Statistics of trials and of the paper's reproduction: one source for both.

Intervals over seeds (Student t, Welch, a paired bootstrap), tests (Welch, Fisher, the
Wilcoxon signed-rank test and its equivalence form), Holm's correction, and the number of
seeds a paired comparison would need. Every function ignores ``nan`` values and answers
``nan`` (or an interval without bounds) where its statistic is undefined, never raises
for too few values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import stats as sps

__all__ = [
    "Interval",
    "bootstrap_interval",
    "first_solved_episode",
    "fisher_p",
    "fmt",
    "fmt_interval",
    "holm",
    "min_signed_rank_p",
    "rolling_mean",
    "seeds_needed",
    "t_interval",
    "welch_interval",
    "welch_p",
    "wilcoxon_equivalence_p",
    "wilcoxon_p",
]

#: Asymptotic relative efficiency of the signed-rank test to the t-test under normality
#: (3/pi): the signed-rank test needs about 1/0.955 times the t-test's seeds.
_WILCOXON_EFFICIENCY = 3.0 / math.pi


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


def _finite(values: Sequence[float] | npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``values`` as a float64 array without its ``nan`` entries."""
    x = np.asarray(values, dtype=np.float64)
    return x[~np.isnan(x)]


def t_interval(values: Sequence[float], confidence: float = 0.95) -> Interval:
    """Student-t confidence interval of the mean of ``values`` (independent seeds)."""
    x = _finite(values)
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
    x = _finite(a)
    y = _finite(b)
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


def bootstrap_interval(
    values: Sequence[float],
    confidence: float = 0.95,
    resamples: int = 10_000,
    seed: int = 0,
) -> Interval:
    """Percentile bootstrap interval of the mean of ``values`` (e.g. paired differences).

    The resampling is seeded, so the same values always give the same interval. With
    fewer than two values the bounds are ``nan``; with all values equal the interval is
    that value.
    """
    x = _finite(values)
    n = int(x.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n == 1:
        return Interval(mean, math.nan, math.nan, 1)
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, n, size=(resamples, n))].mean(axis=1)
    tail = (1 - confidence) / 2
    low, high = np.quantile(means, [tail, 1 - tail])
    return Interval(mean, float(low), float(high), n)


def rolling_mean(values: Sequence[float], window: int) -> npt.NDArray[np.float64]:
    """Trailing mean over up to ``window`` values (shorter at the start)."""
    x = np.asarray(values, dtype=np.float64)
    if x.size == 0:
        return x
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(0, idx - window)
    out: npt.NDArray[np.float64] = (c[idx] - c[lo]) / (idx - lo)
    return out


def first_solved_episode(
    steps: Sequence[float], threshold: float = 195.0, window: int = 100
) -> int | None:
    """Return the first episode (1-based) whose last ``window`` episodes reach ``threshold``.

    ``None`` if never; needs ``window`` full episodes.
    """
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
    x = _finite(a)
    y = _finite(b)
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


def wilcoxon_p(
    differences: Sequence[float] | npt.NDArray[np.float64], alternative: str = "two-sided"
) -> float:
    """p-value of the Wilcoxon signed-rank test that paired ``differences`` centre on 0.

    Zero differences count (Pratt's method: ranked, then dropped), so a pair that did
    exactly the same in both arms weighs against an effect instead of vanishing. The
    p-value is exact for up to 50 pairs without ties, else from the normal approximation.
    ``nan`` with no differences; 1.0 when every difference is zero (nothing to test).
    ``alternative``: ``"two-sided"``, ``"greater"`` (centred above 0) or ``"less"``.
    """
    d = _finite(differences)
    if d.size == 0:
        return math.nan
    if not np.any(d):
        return 1.0
    return float(sps.wilcoxon(d, zero_method="pratt", alternative=alternative).pvalue)


def wilcoxon_equivalence_p(differences: Sequence[float], margin: float) -> float:
    """Return the p-value of the equivalence of the differences within ``±margin``.

    The two one-sided signed-rank tests (TOST) that the paired differences centre strictly
    inside ``(-margin, +margin)``.

    Equivalence is shown at level a when the value is below a: both ``d + margin`` is
    centred above 0 and ``d - margin`` below 0. ``nan`` without differences or with a
    margin that is not positive.
    """
    d = _finite(differences)
    if d.size == 0 or not margin > 0:
        return math.nan
    above = wilcoxon_p(d + margin, "greater")
    below = wilcoxon_p(d - margin, "less")
    return max(above, below)


def min_signed_rank_p(n: int, two_sided: bool = True) -> float:
    """The smallest p-value the exact signed-rank test can give with ``n`` pairs.

    Every difference of one sign, none tied: ``2 / 2**n`` two-sided, ``1 / 2**n`` one-sided.
    Below some n no result can be significant at all (two-sided at 5 %: n < 6).
    """
    if n <= 0:
        return 1.0
    return min(1.0, (2.0 if two_sided else 1.0) / 2.0**n)


def seeds_needed(
    differences: Sequence[float],
    margin: float | None = None,
    alpha: float = 0.05,
    power: float = 0.8,
) -> int | None:
    """Return the pairs of seeds a signed-rank test would need to resolve a comparison.

    At the observed spread of the paired ``differences``.

    The smaller of: the pairs needed to detect the observed mean difference (two-sided at
    ``alpha``, with ``power``), and, when the observed mean lies inside ``margin``, the
    pairs needed to show equivalence within it (one-sided at ``alpha`` each). Normal
    approximation divided by the signed-rank test's efficiency (3/pi), and never fewer
    than the exact test needs to be able to reach ``alpha`` at all. ``None`` when it
    cannot be told (fewer than two differences, or no spread and no mean difference).
    """
    d = _finite(differences)
    if d.size < 2:
        return None
    mean = abs(float(d.mean()))
    sd = float(d.std(ddof=1))
    floor = 2
    while min_signed_rank_p(floor) >= alpha:
        floor += 1
    if sd == 0.0:
        return floor if mean > 0 or (margin is not None and margin > 0) else None
    z_power = float(sps.norm.ppf(power))
    candidates: list[float] = []
    if mean > 0:
        z = float(sps.norm.ppf(1 - alpha / 2))
        candidates.append(((z + z_power) * sd / mean) ** 2 / _WILCOXON_EFFICIENCY)
    if margin is not None and margin > mean:
        z = float(sps.norm.ppf(1 - alpha))
        candidates.append(((z + z_power) * sd / (margin - mean)) ** 2 / _WILCOXON_EFFICIENCY)
    if not candidates:
        return None
    return max(floor, math.ceil(min(candidates)))


def holm(pvalues: Sequence[float]) -> list[float]:
    """Return Holm-Bonferroni adjusted p-values, in the same order.

    ``nan`` entries stay ``nan`` and do not count in the family.
    """
    p = np.asarray(pvalues, dtype=np.float64)
    out = np.full(p.size, math.nan)
    idx = np.flatnonzero(~np.isnan(p))
    m = idx.size
    running = 0.0
    for rank, i in enumerate(idx[np.argsort(p[idx], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    adjusted: list[float] = out.tolist()
    return adjusted


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
