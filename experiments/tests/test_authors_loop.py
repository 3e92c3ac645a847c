"""The authors' loop end to end through a real local server (tiny budgets)."""

import json

import pytest

tamrm = pytest.importorskip("tamrm")

from tamrm_experiments.configs import make_specs  # noqa: E402
from tamrm_experiments.run import run_one, run_paths  # noqa: E402


@pytest.mark.parametrize(("variant", "arm"), [("authors-fixed", "tamrm"), ("authors-neg", "pbrs")])
def test_authors_run_records_fidelity_and_overrides(tmp_path, variant, arm):
    exp = "cartpole" if variant.startswith("authors-f") else "mountaincar"
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
