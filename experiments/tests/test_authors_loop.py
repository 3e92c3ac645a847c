"""The authors' loop end to end through a real local server (tiny budgets)."""

import json

import numpy as np
import pytest

tamrm = pytest.importorskip("tamrm")

from tamrm_experiments.configs import make_specs  # noqa: E402
from tamrm_experiments.run import run_one, run_paths  # noqa: E402


@pytest.mark.parametrize(
    ("exp", "variant", "arm"),
    [
        ("cartpole", "authors-fixed", "tamrm"),
        ("mountaincar", "authors-neg", "pbrs"),
        ("maze", "authors-bug-3", "tamrm"),
    ],
)
def test_authors_run_records_fidelity_and_overrides(tmp_path, exp, variant, arm):
    spec = make_specs("quick", 1, [exp], [arm], variants=[variant])[0]
    with tamrm.local_server() as server:
        meta = run_one(spec, server.address, tmp_path)
    assert meta["spec"]["fidelity"] == "authors"
    assert meta["spec"]["variant"] == variant
    csv_path, _, meta_path = run_paths(tmp_path, spec)
    assert json.loads(meta_path.read_text())["complete"]
    rows = csv_path.read_text().splitlines()[1:]
    assert len(rows) == meta["episodes"] >= 1
    steps = [int(r.split(",")[1]) for r in rows]
    assert sum(steps) == meta["total_steps"]
    if exp == "cartpole":
        # Fixed start: every episode starts from the same state, and the terminal step's
        # reward is overridden to -1 (the shaped return is then below the step count
        # on a failed episode by exactly 2 when no shaping was active).
        first = rows[0].split(",")
        assert int(first[7]) == 1  # terminated
        assert float(first[3]) == pytest.approx(int(first[1]) - 2)
    if exp == "maze":
        # Their score: +-100 / t with t = steps - 1 (the quick budget's episodes time out).
        for r in rows:
            f = r.split(",")
            sign = 1.0 if int(f[7]) else -1.0
            assert float(f[10]) == pytest.approx(sign * 100 / (int(f[1]) - 1))


def test_the_observation_bug_shows_the_learner_only_the_start(monkeypatch):
    from tamrm_experiments import authors

    seen = []

    class Spy(authors.TutorialDQN):
        def act(self, s):
            seen.append(tuple(s))
            return super().act(s)

    monkeypatch.setattr(authors, "TutorialDQN", Spy)
    for variant, expect_one in (("authors-bug-3", True), ("authors-3", False)):
        seen.clear()
        spec = make_specs("quick", 1, ["maze"], ["plain"], variants=[variant])[0]
        with tamrm.local_server() as server, tamrm.Client(server.address) as client:
            client.create_task("t", num_actions=4, **spec.task_config())
            with client.session("t", 1) as session:
                authors.train_authors(spec, session, lambda _row: None, True)
        assert (len(set(seen)) == 1) == expect_one, variant


@pytest.mark.parametrize(
    ("exp", "variant"), [("maze", "authors-tuned-3"), ("cartpole", "authors-fixed")]
)
def test_a_pilot_is_the_plain_run_through_the_server(tmp_path, exp, variant):
    from tamrm_experiments.pilot import pilot

    spec = make_specs("quick", 1, [exp], ["plain"], variants=[variant])[0]
    with tamrm.local_server() as server:
        run_one(spec, server.address, tmp_path)
    rows = run_paths(tmp_path, spec)[0].read_text().splitlines()[1:]
    assert [int(r.split(",")[1]) for r in rows] == pilot(exp, variant, 0, profile="quick")


def test_the_tuned_maze_learner_sees_the_cell_one_hot(monkeypatch):
    from tamrm_experiments import authors
    from tamrm_experiments.pilot import PlainSession

    made, seen = [], []

    class Spy(authors.TutorialDQN):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

        def act(self, s):
            seen.append(np.asarray(s))
            return super().act(s)

    monkeypatch.setattr(authors, "TutorialDQN", Spy)
    for variant, features, hidden in (("authors-tuned-3", 64, 64), ("authors-3", 4, 10)):
        made.clear()
        seen.clear()
        spec = make_specs("quick", 1, ["maze"], ["plain"], variants=[variant])[0]
        authors.train_authors(spec, PlainSession(), lambda _row: None, True)
        (dqn,) = made
        assert dqn.n_features == features
        assert dqn.q.params()[0].shape == (features, hidden)
        if variant == "authors-tuned-3":
            assert all(s.sum() == 1.0 and set(np.unique(s)) == {0.0, 1.0} for s in seen)
            assert dqn.learn_after == 1_000 and dqn.epsilon > 0.9  # decays from 1
        else:
            assert dqn.learn_after == 20_000 and dqn.epsilon == pytest.approx(0.1)


def test_the_modified_maze_authors_run_moves_the_start_and_takes_a_fresh_pool(tmp_path):
    import csv

    from tamrm_experiments.authors import make_authors_env

    spec = make_specs("quick", 1, ["maze_modified"], ["tamrm"], variants=["authors-tuned-3"])[0]
    switch = spec.budget.switch_after
    assert spec.fidelity == "authors" and switch is not None
    env = make_authors_env(spec, {"observation": "onehot"})
    starts = [env.reset()[1]["start"] for _ in range(switch + 2)]
    assert starts[:switch] == [starts[0]] * switch
    assert starts[switch:] == [starts[switch]] * 2 and starts[switch] != starts[0]

    with tamrm.local_server() as server:
        meta = run_one(spec, server.address, tmp_path)
    with open(run_paths(tmp_path, spec)[0]) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == spec.budget.episodes
    assert [int(r["task_phase"]) for r in rows] == [
        0 if int(r["episode"]) <= switch else 1 for r in rows
    ]
    # A second task (a fresh pool) from the switch on; both were deleted at the end.
    assert len(meta["task_ids"]) == 2 and meta["task_ids"][1].startswith(meta["task_ids"][0])
    assert all(p["episodes_completed"] >= 1 for p in meta["final_pools"].values())
    assert sum(p["episodes_completed"] for p in meta["final_pools"].values()) == len(rows)


def test_the_authors_loop_refuses_a_switch_it_cannot_make():
    from tamrm_experiments import authors

    spec = make_specs("quick", 1, ["maze_modified"], ["plain"], variants=["authors-3"])[0]
    with tamrm.local_server() as server, tamrm.Client(server.address) as client:
        client.create_task("t", num_actions=4, **spec.task_config())
        with client.session("t", 1) as session, pytest.raises(ValueError, match="switch_task"):
            authors.train_authors(spec, session, lambda _row: None, True)
