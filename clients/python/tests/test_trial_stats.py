"""The trial's statistics and metrics against naive implementations written from their
definitions (property tests)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip("scipy")

from tamrm.trial.analysis import compare, curve, run_metrics
from tamrm.trial.settings import Margin
from tamrm.trial.stats import (
    bootstrap_interval,
    holm,
    min_signed_rank_p,
    seeds_needed,
    wilcoxon_equivalence_p,
    wilcoxon_p,
)


def naive_signed_rank_p(d: list[float]) -> float:
    """Exact two-sided signed-rank p by enumerating every sign pattern (no ties, no zeros)."""
    n = len(d)
    ranks = np.argsort(np.argsort(np.abs(d))) + 1
    w = sum(r for r, x in zip(ranks, d, strict=True) if x > 0)
    dist = [
        sum(r for r, s in zip(range(1, n + 1), signs, strict=True) if s)
        for signs in itertools.product((0, 1), repeat=n)
    ]
    total = len(dist)
    upper = sum(x >= w for x in dist) / total
    lower = sum(x <= w for x in dist) / total
    return min(1.0, 2 * min(upper, lower))


distinct = st.lists(
    st.integers(min_value=-1000, max_value=1000).filter(lambda x: x != 0),
    min_size=2,
    max_size=9,
    unique_by=abs,
)


@given(distinct)
def test_signed_rank_p_is_the_exact_test(values: list[int]) -> None:
    d = [x / 7 for x in values]
    assert wilcoxon_p(d) == pytest.approx(naive_signed_rank_p(d), rel=1e-9)


@given(st.integers(min_value=1, max_value=12))
def test_min_signed_rank_p_is_all_of_one_sign(n: int) -> None:
    d = list(range(1, n + 1))
    assert min_signed_rank_p(n) == pytest.approx(naive_signed_rank_p(d))
    assert (min_signed_rank_p(n) < 0.05) == (n >= 6)


def test_wilcoxon_edge_cases() -> None:
    assert math.isnan(wilcoxon_p([]))
    assert wilcoxon_p([0.0, 0.0, 0.0]) == 1.0
    assert wilcoxon_p([math.nan, 1.0, 2.0, 3.0]) == wilcoxon_p([1.0, 2.0, 3.0])


def naive_holm(p: list[float]) -> list[float]:
    order = sorted(range(len(p)), key=lambda i: p[i])
    out = [0.0] * len(p)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        out[i] = running
    return out


@given(st.lists(st.floats(min_value=0, max_value=1), min_size=1, max_size=8))
def test_holm_is_holm(p: list[float]) -> None:
    assert holm(p) == pytest.approx(naive_holm(p))


@given(st.lists(st.floats(min_value=-100, max_value=100), min_size=2, max_size=20))
def test_bootstrap_interval_brackets_the_mean_and_repeats(values: list[float]) -> None:
    iv = bootstrap_interval(values)
    assert iv.mean == pytest.approx(float(np.mean(values)))
    assert iv.low <= iv.mean + 1e-9 and iv.mean - 1e-9 <= iv.high
    assert bootstrap_interval(values) == iv  # seeded: the same values, the same interval
    assert min(values) - 1e-9 <= iv.low and iv.high <= max(values) + 1e-9


def test_equivalence() -> None:
    inside = [0.1, -0.2, 0.05, 0.0, 0.15, -0.1, 0.02, -0.05]
    assert wilcoxon_equivalence_p(inside, margin=1.0) < 0.05
    assert wilcoxon_equivalence_p(inside, margin=0.01) > 0.05
    assert math.isnan(wilcoxon_equivalence_p(inside, margin=0.0))
    shifted = [x + 2 for x in inside]  # all outside +1
    assert wilcoxon_equivalence_p(shifted, margin=1.0) > 0.5


def test_seeds_needed() -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(0, 1, 30)
    small = seeds_needed(base + 1.0)
    large = seeds_needed(base + 0.5)
    assert small is not None and large is not None
    assert 2.5 < large / small < 5.5  # half the effect: about four times the seeds
    assert small >= 6  # the exact test cannot reach 5 % below 6 pairs
    # Inside the margin: the pairs to show equivalence.
    eq = seeds_needed(base * 0.1, margin=1.0)
    assert eq is not None and eq >= 6
    assert seeds_needed([1.0]) is None


def naive_curve(returns: list[float], ends: list[int], timesteps: int, points: int) -> list[float]:
    out = []
    value = returns[0]
    for g in range(points):
        lo, hi = timesteps * g / points, timesteps * (g + 1) / points
        inside = [
            r for r, e in zip(returns, ends, strict=True) if (lo < e <= hi) or (g == 0 and e <= hi)
        ]
        if inside:
            value = sum(inside) / len(inside)
        out.append(value)
    return out


episodes = st.lists(
    st.tuples(st.floats(min_value=-50, max_value=50), st.integers(min_value=1, max_value=60)),
    min_size=1,
    max_size=40,
)


@given(episodes, st.integers(min_value=1, max_value=30))
def test_curve_and_metrics_from_their_definitions(
    eps: list[tuple[float, int]], points: int
) -> None:
    returns = [r for r, _ in eps]
    ends = list(np.cumsum([n for _, n in eps]).tolist())
    timesteps = ends[-1]
    record = {"episodes": {"return": returns, "timestep": ends}}
    got = curve(record, timesteps, points)
    assert got.tolist() == pytest.approx(naive_curve(returns, ends, timesteps, points))
    m = run_metrics(record, timesteps, threshold=0.0)
    late = [r for r, e in zip(returns, ends, strict=True) if e > 0.9 * timesteps]
    assert m.final == pytest.approx(
        sum(late) / len(late) if late else float(curve(record, timesteps)[-1])
    )
    # The threshold: the first end at which the mean of the last 10 returns reaches it.
    crossing = None
    for i in range(len(returns)):
        window = returns[max(0, i - 9) : i + 1]
        if sum(window) / len(window) >= 0.0:
            crossing = ends[i]
            break
    assert m.to_threshold == (crossing if crossing is not None else timesteps)
    assert m.censored == (crossing is None)


def test_compare_holm_over_arms_and_verdicts() -> None:
    from tamrm.trial.analysis import RunMetrics

    metrics = {}
    rng = np.random.default_rng(1)
    for seed in range(10):
        base = float(rng.normal(100, 10))
        metrics[("plain", seed)] = RunMetrics(base, base, 10)
        metrics[("null", seed)] = RunMetrics(base, base, 10)
        metrics[("tamrm", seed)] = RunMetrics(base + 30 + seed, base, 10)  # clearly better
        metrics[("knn", seed)] = RunMetrics(base - 40 - seed, base, 10)  # clearly worse
        metrics[("pbrs", seed)] = RunMetrics(base + float(rng.normal(0, 0.5)), base, 10)
    out = {
        c.arm: c
        for c in compare(
            metrics, ("plain", "null", "knn", "pbrs", "tamrm"), Margin(0.1, True), None
        )
    }
    assert set(out) == {"knn", "pbrs", "tamrm"}  # null is the harness check, not compared
    assert out["tamrm"].verdict == "helps" and out["knn"].verdict == "hurts"
    assert out["pbrs"].verdict == "no difference"
    p = [out[a].tests["auc"].p for a in ("knn", "pbrs", "tamrm")]
    assert [out[a].tests["auc"].p_holm for a in ("knn", "pbrs", "tamrm")] == pytest.approx(
        naive_holm(p)
    )
