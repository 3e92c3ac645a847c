import json
import math
from dataclasses import replace

from synthetic import write_run

from tamrm_experiments.configs import ARMS, make_specs
from tamrm_experiments.report import load_runs, run_metrics, write_report
from tamrm_experiments.run import run_paths
from tamrm_experiments.stats import t_interval


def test_report_tables_from_synthetic_runs(tmp_path):
    runs = tmp_path / "runs"
    totals = {}
    for spec in make_specs("quick", seeds=3, experiments=["maze"], variants=["clean"]):
        # TAMRM clearly needs fewer steps than plain; the others are in between.
        base = {"plain": 100, "pbrs": 90, "knn": 80, "tamrm": 20}[spec.arm] + spec.seed
        steps = [base] * spec.budget.episodes
        totals.setdefault(spec.arm, []).append(sum(steps))
        write_run(runs, spec, steps)
    loaded = load_runs(runs)
    assert len(loaded) == 12
    assert {run_metrics(r)["total_steps"] for r in loaded if r.arm == "tamrm"} == set(
        map(float, totals["tamrm"])
    )
    out = tmp_path / "docs" / "reproduction.md"
    write_report(runs, out, tmp_path / "docs" / "reproduction")
    text = out.read_text()
    assert (tmp_path / "docs" / "reproduction" / "maze-clean.png").is_file()
    iv = t_interval(totals["tamrm"])
    assert f"{iv.mean:,.0f} [{iv.low:,.0f}, {iv.high:,.0f}]" in text
    assert "(reproduction/maze-clean.png)" in text
    claims = text.split("## Claims")[1].split("## Status")[0]
    tamrm_row = next(line for line in claims.splitlines() if "TAMRM needs fewer" in line)
    assert "**holds**" in tamrm_row
    # PBRS needs fewer steps than plain here, against the paper's claim of more.
    pbrs_row = next(line for line in claims.splitlines() if "PBRS alone" in line)
    assert "**does not hold**" in pbrs_row
    for arm in ARMS.values():
        assert arm.label in text


def test_a_claim_with_seeds_pending_cannot_be_decided(tmp_path):
    runs = tmp_path / "runs"
    for spec in make_specs("quick", seeds=2, experiments=["maze"], variants=["clean"]):
        write_run(runs, spec, [50 + spec.seed] * spec.budget.episodes)
    with open(runs / "invocations.jsonl", "w") as fh:
        cmd = "python -m tamrm_experiments run --quick --experiments maze --variants clean"
        fh.write(json.dumps({"command": cmd + " --seeds 5", "runs_todo": 1}) + "\n")
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    claims = out.read_text().split("## Claims")[1].split("## Status")[0]
    row = next(line for line in claims.splitlines() if "TAMRM needs fewer" in line)
    assert "**cannot be decided yet**" in row and "2 of 5 seeds" in row


def test_report_flags_an_experiment_whose_runs_mix_budgets(tmp_path):
    runs = tmp_path / "runs"
    specs = make_specs("quick", seeds=2, experiments=["maze"], variants=["clean"])
    for spec in specs:
        write_run(runs, spec, [50] * spec.budget.episodes)
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    assert "Mixed budgets" not in out.read_text()
    # One run redone under another budget (e.g. the profile changed mid-grid).
    longer = replace(specs[0], budget=replace(specs[0].budget, episodes=9))
    write_run(runs, longer, [50] * 9)
    write_report(runs, out, tmp_path / "plots")
    section = out.read_text().split("## Maze: clean")[1]
    assert "Mixed budgets" in section


def test_status_lists_only_runs_some_invocation_asked_for(tmp_path):
    runs = tmp_path / "runs"
    for spec in make_specs("quick", seeds=1, experiments=["maze"], variants=["clean"]):
        write_run(runs, spec, [50] * spec.budget.episodes)
    commands = [
        "python -m tamrm_experiments run --quick --experiments maze --variants clean",
        # Extra seeds for one arm only: the other arms' seed 1 is not missing.
        "python -m tamrm_experiments run --quick --experiments maze --variants clean "
        "--arms plain --seeds 3",
    ]
    with open(runs / "invocations.jsonl", "w") as fh:
        for c in commands:
            fh.write(json.dumps({"command": c, "runs_todo": 1}) + "\n")
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    status = out.read_text().split("## Status of the grid")[1].split("## Pilot")[0]
    plain = next(line for line in status.splitlines() if "plain (no shaping)" in line)
    assert "| 2: 1, 2 |" in plain
    knn = next(line for line in status.splitlines() if "kNN only" in line)
    assert knn.endswith("| 0 |")
    assert "4 of the 6 runs of the current grid asked for" in out.read_text()


def test_report_does_not_import_the_cli():
    import subprocess
    import sys

    code = "import sys, tamrm_experiments.report; print('tamrm_experiments.cli' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.strip() == "False"


def test_each_experiment_module_defines_its_table_and_budgets():
    from tamrm_experiments.configs import EXPERIMENTS, PROFILES

    for name, exp in EXPERIMENTS.items():
        assert exp.headline in {m.key for m in exp.metrics}, name
        assert set(exp.paper) == set(ARMS), name
        for profile in PROFILES.values():
            assert profile.budgets[name] == exp.budgets[profile.name]


def test_previous_runs_show_as_the_first_reports_variant(tmp_path):
    runs, previous = tmp_path / "runs", tmp_path / "runs-v1"
    runs.mkdir()
    for spec in make_specs("quick", seeds=2, experiments=["maze"], variants=["clean"]):
        # The first report's layout and spec: no variant, no fidelity.
        spec_dict = spec.to_dict()
        for key in ("variant", "fidelity", "variant_settings"):
            spec_dict.pop(key)
        write_run(previous, spec, [60 + spec.seed] * spec.budget.episodes)
        meta_path = run_paths(previous, spec)[2]
        meta = json.loads(meta_path.read_text())
        meta["spec"] = spec_dict
        meta_path.write_text(json.dumps(meta))
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots", previous)
    text = out.read_text()
    assert "## Maze: clean, first report" in text
    claims = text.split("## Claims")[1].split("## Status")[0]
    assert "clean, first report" in claims
    # Nothing of it is pending.
    status = text.split("## Status of the grid")[1].split("## Pilot")[0]
    assert all(line.endswith("| 0 |") for line in status.splitlines() if "first report" in line)


def test_labels_fit_in_a_markdown_table_cell():
    from tamrm_experiments.configs import EXPERIMENTS

    labels = [v.label for e in EXPERIMENTS.values() for v in e.variants]
    labels += [a.label for a in ARMS.values()] + [e.title for e in EXPERIMENTS.values()]
    assert not [label for label in labels if "|" in label]


def test_a_large_variable_effect_that_fails_holm_is_not_called_small():
    from tamrm_experiments.experiments.base import Claim
    from tamrm_experiments.report import ClaimRow

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
    from tamrm_experiments.experiments.base import Claim
    from tamrm_experiments.report import ClaimRow

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


def test_update_readme_rewrites_only_the_generated_block(tmp_path):
    import pytest

    from tamrm_experiments.report import README_BEGIN, README_END, readme_block, update_readme

    readme = tmp_path / "README.md"
    readme.write_text(
        f"# title\n\nhand text\n{README_BEGIN}\nold\n{README_END}\n\nmore hand text\n"
    )
    assert update_readme(readme, ["new line 1", "", "new line 2"])
    text = readme.read_text()
    assert readme_block(text) == "new line 1\n\nnew line 2"
    assert text.startswith("# title\n\nhand text\n") and text.endswith("\n\nmore hand text\n")
    assert not update_readme(readme, ["new line 1", "", "new line 2"])  # idempotent
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match="no lines"):
        update_readme(readme, ["x"])


def test_the_readme_summary_follows_the_packed_runs(tmp_path):
    """The README's table is what the report computes from the runs it ships with
    (docs/reproduction/raw-runs.tar.gz): regenerate it and compare, line by line."""
    import tarfile
    from pathlib import Path

    from tamrm_experiments.report import analyse, readme_block, readme_summary

    root = Path(__file__).resolve().parents[2]
    with tarfile.open(root / "docs/reproduction/raw-runs.tar.gz") as tar:
        tar.extractall(tmp_path, filter="data")
    summary = readme_summary(analyse(tmp_path / "runs", tmp_path / "runs-v1"))
    block = readme_block((root / "README.md").read_text())
    assert block is not None, "README.md lost its reproduction-summary markers"
    assert block.splitlines() == summary, (
        "README.md's reproduction summary is stale: run `python -m tamrm_experiments "
        "report --runs runs --previous runs-v1 --readme ../README.md` from experiments/"
    )


def test_identical_rows_are_one_test_in_the_holm_family():
    from tamrm_experiments.report import _adjust, _distinct_tests
    from tamrm_experiments.stats import holm

    plain = [100.0, 102.0, 98.0, 101.0, 99.0] * 2
    fewer = [96.0, 99.0, 97.0, 98.0, 95.0] * 2
    other = [99.0, 103.0, 97.0, 100.0, 98.0] * 2
    # The same samples in two variants (pool 3 and pool 10 of an arm that reads no pool).
    rows = [
        _row(fewer, plain, math.nan),
        _row(other, plain, math.nan),
        _row(fewer, plain, math.nan),
    ]
    _adjust(rows)
    assert _distinct_tests(rows) == 2
    expected = holm([rows[0].p, rows[1].p])
    assert [r.p_holm for r in rows] == [expected[0], expected[1], expected[0]]
    # Counted three times, the family would adjust more: the duplicate must not count.
    assert holm([r.p for r in rows])[0] > rows[0].p_holm
    # A different metric on the same numbers is a different test.
    rows[2].claim = replace(rows[2].claim, metric="solved")
    assert _distinct_tests(rows) == 3
