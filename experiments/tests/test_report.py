import json
from dataclasses import replace

from synthetic import write_run
from tamrm.trial.stats import t_interval

from tamrm_experiments.configs import ARMS, make_specs
from tamrm_experiments.report import load_runs, run_metrics, write_report
from tamrm_experiments.run import run_paths


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
    claims = text.split("### In detail")[1].split("## Status")[0]
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
    claims = out.read_text().split("### In detail")[1].split("## Status")[0]
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
    claims = text.split("### In detail")[1].split("## Status")[0]
    assert "clean, first report" in claims
    # Nothing of it is pending.
    status = text.split("## Status of the grid")[1].split("## Pilot")[0]
    assert all(line.endswith("| 0 |") for line in status.splitlines() if "first report" in line)


def test_labels_fit_in_a_markdown_table_cell():
    from tamrm_experiments.configs import EXPERIMENTS

    labels = [v.label for e in EXPERIMENTS.values() for v in e.variants]
    labels += [a.label for a in ARMS.values()] + [e.title for e in EXPERIMENTS.values()]
    assert not [label for label in labels if "|" in label]
