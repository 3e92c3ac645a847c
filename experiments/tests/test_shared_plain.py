"""The plain arm runs once per set of variants that differ only in shaping settings."""

import json
from dataclasses import replace

import pytest
from synthetic import write_run

from tamrm_experiments.configs import EXPERIMENTS, make_specs, plain_key, runs_variant
from tamrm_experiments.report import write_report

MC = EXPERIMENTS["mountaincar"]


def test_mountain_car_plain_runs_once_for_both_signs():
    specs = make_specs(
        "paper",
        seeds=2,
        experiments=["mountaincar"],
        variants=["authors-neg", "authors-pos"],
        arms=["plain", "tamrm"],
    )
    assert [s.key for s in specs] == [
        "mountaincar/authors-neg/plain/seed0",
        "mountaincar/authors-neg/tamrm/seed0",
        "mountaincar/authors-pos/tamrm/seed0",
        "mountaincar/authors-neg/plain/seed1",
        "mountaincar/authors-neg/tamrm/seed1",
        "mountaincar/authors-pos/tamrm/seed1",
    ]
    # Asking for authors-pos alone still runs its plain arm: as the shared run.
    pos = make_specs("paper", seeds=1, variants=["authors-pos"], arms=["plain"])
    assert [s.key for s in pos] == ["mountaincar/authors-neg/plain/seed0"]
    assert pos[0].task_config()["alpha"] == pos[0].task_config()["beta"] == 0.0


def test_the_tamrm_arms_keep_their_own_signs():
    neg, pos = (
        make_specs("paper", seeds=1, variants=[v], arms=["tamrm"])[0]
        for v in ("authors-neg", "authors-pos")
    )
    assert (neg.task_config()["alpha"], pos.task_config()["alpha"]) == (-1.0, 1.0)
    assert runs_variant(MC, "authors-pos", "tamrm") == "authors-pos"
    assert runs_variant(MC, "authors-pos", "plain") == "authors-neg"
    assert runs_variant(MC, "authors-neg", "plain") == "authors-neg"


def test_clean_gated_shares_the_plain_runs_of_clean():
    for name in ("cartpole", "mountaincar", "maze"):
        gated = make_specs("paper", seeds=1, experiments=[name], variants=["clean-gated"])
        assert {s.variant for s in gated if s.arm == "plain"} == {"clean"}
        assert {s.variant for s in gated if s.arm != "plain"} == {"clean-gated"}
        both = make_specs("paper", seeds=1, experiments=[name], variants=["clean", "clean-gated"])
        assert sum(s.arm == "plain" for s in both) == 1
        assert len(both) == 7


def test_maze_pool_sizes_share_the_plain_arm():
    maze = EXPERIMENTS["maze"]
    for small, large in (("authors-3", "authors-10"), ("authors-tuned-3", "authors-tuned-10")):
        assert runs_variant(maze, large, "plain") == small
        assert runs_variant(maze, large, "tamrm") == large
        specs = make_specs("paper", 1, ["maze"], ["plain", "knn"], variants=[small, large])
        assert [s.key for s in specs] == [
            f"maze/{small}/plain/seed0",
            f"maze/{small}/knn/seed0",
            f"maze/{large}/knn/seed0",
        ]
        assert specs[1].task_config()["pool_capacity"] == 3
        assert specs[2].task_config()["pool_capacity"] == 10
    # The observation bug is not a shaping setting: its variants run their own plain.
    assert runs_variant(maze, "authors-bug-3", "plain") == "authors-bug-3"
    assert plain_key(maze, maze.variant("authors-bug-3")) != plain_key(
        maze, maze.variant("authors-3")
    )


def test_every_declared_share_has_the_same_plain_settings():
    shares = [(e, v) for e in EXPERIMENTS.values() for v in e.variants if v.plain_from]
    assert shares
    for exp, var in shares:
        assert plain_key(exp, var) == plain_key(exp, exp.variant(var.plain_from))


def _with_variant(exp, name, **changes):
    variants = tuple(replace(v, **changes) if v.name == name else v for v in exp.variants)
    return replace(exp, variants=variants)


def test_a_share_between_variants_whose_plain_differs_is_refused(monkeypatch):
    pos = MC.variant("authors-pos")
    # Only signs differ: the same plain.
    assert plain_key(MC, pos) == plain_key(MC, MC.variant("authors-neg"))
    # A different terminal override, learner or budget is not a shaping setting.
    for settings in (
        {**pos.settings, "terminal_reward": 0.0},
        {**pos.settings, "learner": "maze_dqn"},
        {**pos.settings, "tamrm": {**pos.settings["tamrm"], "gamma": 0.99}},
    ):
        changed = _with_variant(MC, "authors-pos", settings=settings)
        assert plain_key(changed, changed.variant("authors-pos")) != plain_key(
            changed, changed.variant("authors-neg")
        )
        monkeypatch.setitem(EXPERIMENTS, "mountaincar", changed)
        with pytest.raises(ValueError, match="plain_from"):
            make_specs("paper", seeds=1, variants=["authors-pos"], arms=["plain"])
    monkeypatch.setitem(EXPERIMENTS, "mountaincar", MC)


def test_report_compares_both_signs_with_the_one_plain_run(tmp_path):
    runs = tmp_path / "runs"
    specs = make_specs(
        "quick", seeds=3, experiments=["mountaincar"], variants=["authors-neg", "authors-pos"]
    )
    specs = [s for s in specs if s.arm in ("plain", "tamrm")]
    plain_steps = {}
    for s in specs:
        if s.arm == "plain":
            plain_steps[s.seed] = [300 + 10 * s.seed, 200]
            write_run(runs, s, plain_steps[s.seed])
        else:  # authors-neg: fewer steps than plain; authors-pos: more
            delta = -150 if s.variant == "authors-neg" else 400
            write_run(runs, s, [300 + delta + 10 * s.seed, 200])
    plain0 = next(s for s in specs if s.arm == "plain" and s.seed == 0)
    plain1 = next(s for s in specs if s.arm == "plain" and s.seed == 1)
    # Plain runs made under authors-pos's own name before the sharing: one replays the
    # shared run of its seed, the other does not; neither enters the statistics.
    write_run(runs, plain0, plain_steps[0], variant="authors-pos")
    write_run(runs, plain1, [5, 5], variant="authors-pos")
    (runs / "invocations.jsonl").write_text(
        json.dumps(
            {
                "command": "python -m tamrm_experiments run --profile quick --seeds 3 "
                "--experiments mountaincar --variants authors-neg authors-pos "
                "--arms plain tamrm",
                "runs_todo": 9,
                "status": "started",
            }
        )
        + "\n"
    )
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    text = out.read_text()
    claims = text.split("### In detail")[1].split("## Status")[0]
    rows = [line for line in claims.splitlines() if line.startswith("| Mountain car")]
    assert len(rows) == 2
    neg = next(r for r in rows if "alpha = beta = -1" in r)
    pos = next(r for r in rows if "alpha = beta = +1" in r)
    # Both compare with the three shared plain runs: plain mean 510 (= 300 + 10 + 200).
    for row in (neg, pos):
        assert "plain 510.0 [" in row
    assert "**holds**" in neg
    assert "**does not hold**" in pos
    status = text.split("## Status of the grid")[1].split("## Pilot")[0]
    pos_plain = next(
        line for line in status.splitlines() if "+1" in line and "plain (no shaping)" in line
    )
    assert "(the runs of authors-neg)" in pos_plain
    assert "3: 0-2 | 0 |" in pos_plain  # done, nothing pending
    assert "seeds 0, 1), kept in the raw data: 1 identical" in status
    assert "1 different (seeds 1)" in status
    assert "## Mountain car: authors (their DQN, the paper's signs" in text
    assert "The plain arm is shared with *authors (their DQN, their signs" in text


def test_a_variant_with_only_shared_runs_gets_no_section(tmp_path):
    runs = tmp_path / "runs"
    for spec in make_specs("quick", seeds=2, experiments=["maze"], variants=["clean"]):
        write_run(runs, spec, [50, 40, 30, 20, 10, 10])
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    text = out.read_text()
    # clean's plain runs are also clean-gated's, but nobody asked for clean-gated.
    assert "## Maze: clean (SB3, gate_potential off)" in text
    assert "gate_potential on" not in text
    assert not (tmp_path / "plots" / "maze-clean-gated.png").exists()
