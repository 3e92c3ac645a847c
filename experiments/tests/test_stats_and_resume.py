import json
import math

import numpy as np
import pytest
from scipy import stats as sps
from tamrm.trial.stats import (
    first_solved_episode,
    rolling_mean,
    t_interval,
    welch_interval,
)

from tamrm_experiments.configs import make_specs
from tamrm_experiments.run import is_complete, run_paths


def test_t_interval_matches_scipy():
    data = [3.1, 4.7, 2.2, 5.9, 4.4, 3.8]
    iv = t_interval(data)
    lo, hi = sps.t.interval(0.95, len(data) - 1, loc=np.mean(data), scale=sps.sem(data))
    assert iv.mean == pytest.approx(np.mean(data))
    assert iv.low == pytest.approx(lo)
    assert iv.high == pytest.approx(hi)
    assert iv.n == 6


def test_t_interval_edge_cases():
    assert math.isnan(t_interval([]).mean)
    one = t_interval([2.0])
    assert one.mean == 2.0 and math.isnan(one.low)
    const = t_interval([1.0, 1.0, 1.0])
    assert (const.low, const.high) == (1.0, 1.0)
    assert t_interval([1.0, float("nan"), 3.0]).n == 2


def test_welch_matches_scipy():
    a = [10.0, 12.0, 9.5, 11.0, 13.5]
    b = [7.0, 8.5, 6.0, 9.0, 7.5, 8.0]
    iv = welch_interval(a, b)
    res = sps.ttest_ind(a, b, equal_var=False)
    ci = res.confidence_interval(0.95)
    assert iv.mean == pytest.approx(np.mean(a) - np.mean(b))
    assert iv.low == pytest.approx(ci.low)
    assert iv.high == pytest.approx(ci.high)
    assert iv.excludes(0.0)


def test_rolling_and_solved():
    assert list(rolling_mean([1, 2, 3, 4], 2)) == [1, 1.5, 2.5, 3.5]
    steps = [100] * 150 + [200] * 200
    # mean of the last 100 reaches 195 once 95 of them are 200: episode 150 + 95
    assert first_solved_episode(steps) == 245
    assert first_solved_episode([200] * 99) is None
    assert first_solved_episode([200] * 100) == 100
    assert first_solved_episode([150] * 500) is None


def test_complete_run_is_skipped_and_partial_is_not(tmp_path):
    spec = make_specs("quick", seeds=1, experiments=["maze"], arms=["plain"])[0]
    assert not is_complete(tmp_path, spec)
    csv_path, partial, meta_path = run_paths(tmp_path, spec)
    csv_path.parent.mkdir(parents=True)
    partial.write_text("episode\n1\n")
    assert not is_complete(tmp_path, spec)
    csv_path.write_text("episode\n1\n")
    meta_path.write_text(json.dumps({"complete": True, "spec": spec.to_dict()}))
    assert is_complete(tmp_path, spec)
    # A different budget (e.g. a later, longer run) is not the same run.
    other = make_specs("full", seeds=1, experiments=["maze"], arms=["plain"])[0]
    assert run_paths(tmp_path, other)[0] == csv_path
    assert not is_complete(tmp_path, other)
    meta_path.write_text("{not json")
    assert not is_complete(tmp_path, spec)


def test_grid_is_seed_major_and_selects_by_fidelity_and_variant():
    from tamrm_experiments.configs import EXPERIMENTS

    variants = [v for e in EXPERIMENTS.values() for v in e.variants if v.runnable]
    # Four arms per variant, less the plain arms shared with another variant.
    per_seed = 4 * len(variants) - sum(v.plain_from is not None for v in variants)
    specs = make_specs("full", seeds=2)
    assert len(specs) == 2 * per_seed
    assert {s.seed for s in specs[:per_seed]} == {0}
    assert len({s.key for s in specs}) == len(specs)
    authors = make_specs("paper", seeds=1, fidelities=["authors"])
    assert authors and {s.fidelity for s in authors} == {"authors"}
    # Every experiment has both fidelities (the authors' and the clean one).
    assert {s.experiment for s in authors} == set(EXPERIMENTS)
    clean = make_specs("paper", seeds=1, fidelities=["clean"])
    assert {s.experiment for s in clean} == set(EXPERIMENTS)
    fixed = make_specs("paper", seeds=1, variants=["authors-fixed"], arms=["tamrm"])
    assert [s.key for s in fixed] == ["cartpole/authors-fixed/tamrm/seed0"]
    cfg = fixed[0].to_dict()
    assert cfg["fidelity"] == "authors"
    assert cfg["task_config"]["gate_potential"] is True
    assert (cfg["task_config"]["start_step"], cfg["task_config"]["k"]) == (8, 20)
    pbrs = make_specs("paper", seeds=1, variants=["authors-neg"], arms=["pbrs"])[0]
    tc = pbrs.task_config()
    assert (tc["alpha"], tc["beta"], tc["gate_potential"]) == (0.0, -1.0, False)
    gated = make_specs("paper", seeds=1, variants=["clean-gated"], arms=["tamrm"])
    assert all(s.task_config()["gate_potential"] for s in gated)
    assert not any(
        s.task_config()["gate_potential"] for s in make_specs("paper", 1, variants=["clean"])
    )


def test_busy_minutes_is_the_union_of_invocation_intervals():
    from tamrm_experiments.grid import busy_minutes

    def inv(start, finish):
        return {
            "started_utc": f"2026-01-01T{start}:00Z",
            "finished_utc": f"2026-01-01T{finish}:00Z",
        }

    # Overlapping and nested invocations count once; the gap between sessions not at all.
    invs = [
        inv("00:00", "01:00"),
        inv("00:30", "01:30"),
        inv("03:00", "03:10"),
        inv("00:10", "00:20"),
    ]
    assert busy_minutes(invs) == 100
    assert busy_minutes([*invs, {"started_utc": "2026-01-01T05:00:00Z"}]) == 100  # unfinished
    assert busy_minutes([]) == 0


def test_holm_matches_the_textbook_example():
    from tamrm.trial.stats import holm

    # m = 4: sorted 0.01, 0.02, 0.03, 0.5 -> 0.04, 0.06, 0.06 (monotone), 0.5
    assert holm([0.03, 0.5, 0.01, 0.02]) == pytest.approx([0.06, 0.5, 0.04, 0.06])
    out = holm([0.04, float("nan")])
    assert out[0] == pytest.approx(0.04) and math.isnan(out[1])


def test_welch_and_fisher_p():
    from tamrm.trial.stats import fisher_p, welch_p

    a, b = [10.0, 12.0, 9.5, 11.0, 13.5], [7.0, 8.5, 6.0, 9.0, 7.5, 8.0]
    assert welch_p(a, b) == pytest.approx(sps.ttest_ind(a, b, equal_var=False).pvalue)
    assert math.isnan(welch_p([1.0], b))
    assert fisher_p(10, 10, 0, 10) < 0.001
    assert fisher_p(5, 10, 5, 10) == pytest.approx(1.0)
