"""Verdicts: the claims' tests, Holm's correction over distinct tests, censoring, metrics."""

import math
from dataclasses import replace

import pandas as pd
from hypothesis import given, settings
from hypothesis import strategies as st
from tamrm.trial.stats import holm, welch_interval

from tamrm_experiments.configs import make_specs
from tamrm_experiments.experiments.base import Claim, Metric
from tamrm_experiments.load import Run
from tamrm_experiments.verdicts import (
    ClaimRow,
    Comparison,
    adjust,
    censoring_caveat,
    distinct_tests,
    run_metrics,
)


def test_a_large_variable_effect_that_fails_holm_is_not_called_small():
    claim = Claim("PBRS alone needs more", "10x", "pbrs", "total_steps", +1)
    # Ten seeds far above plain on average, but spread widely.
    arm = [10_000.0, 20_000.0, 900_000.0, 50_000.0, 700_000.0] * 2
    plain = [9_800.0, 10_100.0, 9_900.0, 10_000.0, 10_200.0] * 2
    row = ClaimRow("maze", "v", claim, arm, plain, planned=10)
    row.measure()
    assert row.p < 0.05 and row.diff.mean > 0
    row.p_holm = 0.053  # as if corrected over many tests
    word, why = row.verdict()
    assert word == "does not hold"
    assert "points the claimed way" in why and "smaller than" not in why
    # The same row with a small estimate keeps the old sentence.
    small = ClaimRow("maze", "v", claim, [10_050.0, 9_950.0] * 5, plain, planned=10)
    small.measure()
    small.p_holm = 1.0
    assert "smaller than these seeds resolve" in small.verdict()[1]


def _row(arm, plain, p_holm, planned=10, direction=-1):
    claim = Claim("TAMRM needs fewer steps", "-7%", "tamrm", "total_steps", direction)
    row = ClaimRow("maze", "clean", claim, arm, plain, planned=planned)
    row.measure()
    row.p_holm = p_holm
    return row


def test_the_short_verdict_says_the_same_as_the_long_one():
    plain = [100.0, 102.0, 98.0, 101.0, 99.0] * 2
    fewer = [50.0, 52.0, 48.0, 51.0, 49.0] * 2
    more = [150.0, 152.0, 148.0, 151.0, 149.0] * 2
    cases = [
        (_row(fewer, plain, 0.001), "holds", "**holds**"),
        (_row(more, plain, 0.001), "does not hold", "significant the other way"),
        (_row(fewer, plain, 0.2), "does not hold", "the claimed way, not significant after Holm"),
        (_row(more, plain, 0.2), "does not hold", "the other way, not significant after Holm"),
        (_row([v + 0.5 for v in plain], plain, 1.0), "does not hold", "no significant difference"),
        (_row(fewer[:4], plain[:4], 0.2, planned=10), "cannot be decided yet", "4 of 10 seeds"),
        (_row(fewer[:1], plain, math.nan), "cannot be decided yet", "1 of 10 seeds"),
    ]
    for row, word, short in cases:
        assert row.verdict()[0] == word
        assert row.short_verdict().startswith(f"**{word}**")
        assert short in row.short_verdict()


def test_identical_rows_are_one_test_in_the_holm_family():
    plain = [100.0, 102.0, 98.0, 101.0, 99.0] * 2
    fewer = [96.0, 99.0, 97.0, 98.0, 95.0] * 2
    other = [99.0, 103.0, 97.0, 100.0, 98.0] * 2
    # The same samples in two variants (pool 3 and pool 10 of an arm that reads no pool).
    rows = [
        _row(fewer, plain, math.nan),
        _row(other, plain, math.nan),
        _row(fewer, plain, math.nan),
    ]
    adjust(rows)
    assert distinct_tests(rows) == 2
    expected = holm([rows[0].p, rows[1].p])
    assert [r.p_holm for r in rows] == [expected[0], expected[1], expected[0]]
    # Counted three times, the family would adjust more: the duplicate must not count.
    assert holm([r.p for r in rows])[0] > rows[0].p_holm
    # A different metric on the same numbers is a different test.
    rows[2].claim = replace(rows[2].claim, metric="solved")
    assert distinct_tests(rows) == 3


samples = st.sampled_from(
    [
        (96.0, 99.0, 97.0, 98.0),
        (50.0, 52.0, 48.0, 51.0),
        (100.0, 101.0, 99.0, 100.5),
        (130.0, 90.0, 170.0, 110.0),
        (99.0, 99.0, 99.0, 99.0),
    ]
)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(samples, st.sampled_from(["total_steps", "last20"])), max_size=8))
def test_holm_counts_each_distinct_test_once(specs):
    """Against the formula: the distinct (metric, samples) tests sorted by p, the i-th
    (from 0) adjusted to max over j <= i of min(1, (m - j) p_j), m the distinct tests."""
    plain = [100.0, 102.0, 98.0, 101.0]
    rows = []
    for arm, metric in specs:
        claim = Claim("c", "p", "tamrm", metric, -1)
        row = ClaimRow("maze", "v", claim, list(arm), plain, planned=4)
        row.measure()
        rows.append(row)
    adjust(rows)
    tests = {}
    for row in rows:
        tests.setdefault(row.test_key, row.p)
    ranked = sorted((p, k) for k, p in tests.items() if not math.isnan(p))
    expected, running = {}, 0.0
    for j, (p, k) in enumerate(ranked):
        running = max(running, min(1.0, (len(ranked) - j) * p))
        expected[k] = running
    assert distinct_tests(rows) == len(ranked)
    for row in rows:
        if math.isnan(row.p):
            assert math.isnan(row.p_holm)
        else:
            assert math.isclose(row.p_holm, expected[row.test_key], rel_tol=1e-12)


def _comparison(better):
    metric = Metric("total_steps", "total steps", True)
    return Comparison("tamrm", metric, welch_interval([1.0, 2.0], [3.0, 4.0]), better, "t")


def test_censoring_keeps_only_verdicts_it_cannot_reverse():
    # Totals of censored runs are lower bounds: a censored plain can only be worse than
    # measured, a censored arm only worse too. What survives, per (arm, plain) censored:
    for arm_c, plain_c, better, kept in [
        (False, True, True, True),  # plain even slower: "arm better" stands
        (False, True, False, False),
        (True, False, False, True),  # arm even slower: "arm worse" stands
        (True, False, True, False),
        (True, True, True, False),  # both bounds: nothing is safe
        (True, True, False, False),
    ]:
        comp = censoring_caveat(_comparison(better), arm_c, plain_c)
        assert (comp.better is better) == kept, (arm_c, plain_c, better)
        assert ("counted as undecided" in comp.text) == (not kept)
    undecided = censoring_caveat(_comparison(None), True, False)
    assert undecided.better is None and undecided.text.endswith("(some totals are lower bounds)")


def test_the_unfinished_episode_of_a_capped_run_counts_in_its_total():
    spec = make_specs("quick", seeds=1, experiments=["maze"], arms=["plain"])[0]
    df = pd.DataFrame({"steps": [10, 20, 30], "success": [1, 0, 1]})
    meta = {"spec": spec.to_dict(), "total_steps": 75, "censored": True}
    run = Run("maze", "plain", 0, meta, df, spec.variant)
    m = run_metrics(run)
    assert m["total_steps"] == 75.0  # 60 in finished episodes, 15 in the cut one
    assert (m["episodes"], m["last20"], m["successes"]) == (3.0, 20.0, 2.0)
    # A run whose sidecar counts no more than its episodes adds nothing.
    assert run_metrics(replace(run, meta={**meta, "total_steps": 60}))["total_steps"] == 60.0
