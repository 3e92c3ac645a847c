"""Where a run's shaping is computed: an embedded engine of its own by default, the
server at ``--address`` when given; each run's sidecar records which."""

import json

import pytest

tamrm = pytest.importorskip("tamrm")

from synthetic import write_run  # noqa: E402

from tamrm_experiments import cli  # noqa: E402
from tamrm_experiments.args import parser  # noqa: E402
from tamrm_experiments.configs import make_specs  # noqa: E402
from tamrm_experiments.report import load_runs, write_report  # noqa: E402
from tamrm_experiments.run import run_one, run_paths  # noqa: E402

# One short run: the authors' cart pole (fixed start), TAMRM arm, quick budget.
ONE_RUN = ["--quick", "--experiments", "cartpole", "--variants", "authors-fixed"]
ONE_RUN += ["--arms", "tamrm", "--seeds", "1", "--jobs", "1", "--no-progress"]


def _spec():
    (spec,) = make_specs("quick", 1, ["cartpole"], ["tamrm"], variants=["authors-fixed"])
    return spec


@pytest.fixture
def made(monkeypatch):
    """Every Engine and Client the run makes, as ("engine", None) or ("server", address)."""
    made = []

    class Engine(tamrm.Engine):
        def __init__(self, *args, **kwargs):
            made.append(("engine", None))
            super().__init__(*args, **kwargs)

    class Client(tamrm.Client):
        def __init__(self, target=None, *args, **kwargs):
            made.append(("server", target))
            super().__init__(target, *args, **kwargs)

    monkeypatch.setattr(tamrm, "Engine", Engine)
    monkeypatch.setattr(tamrm, "Client", Client)
    return made


def test_the_command_line_has_no_address_unless_given():
    assert parser().parse_args(["run"]).address is None
    assert parser().parse_args(["run", "--address", "h:50051"]).address == "h:50051"


def test_a_run_without_an_address_shapes_on_an_engine_of_its_own(tmp_path, made):
    meta = run_one(_spec(), None, tmp_path)
    assert made == [("engine", None)]
    assert meta["backend"] == "engine"
    assert meta["versions"]["tamrm_engine_sha256"] != "unknown"
    assert "tamrm_server" not in meta["versions"]
    on_disk = json.loads(run_paths(tmp_path, _spec())[2].read_text())
    assert on_disk["backend"] == "engine" and on_disk["complete"]


def test_a_run_with_an_address_shapes_on_that_server(tmp_path, made):
    with tamrm.local_server() as server:
        meta = run_one(_spec(), server.address, tmp_path)
    assert made == [("server", server.address)]
    assert meta["backend"] == "server"
    assert "tamrm_server" in meta["versions"]
    assert "tamrm_engine_sha256" not in meta["versions"]


def _summary(out):
    lines = (out / "invocations.jsonl").read_text().splitlines()
    return json.loads(lines[-1])


def test_the_grid_runs_on_the_engine_by_default_and_starts_no_server(tmp_path, monkeypatch):
    def no_server(*_args, **_kwargs):
        raise AssertionError("the default backend must not start a server")

    monkeypatch.setattr(tamrm, "local_server", no_server)
    # Nor may a run look for one: a server binary that cannot exist.
    monkeypatch.setenv("TAMRM_BIN", str(tmp_path / "no-such-tamrm"))
    assert cli.main(["run", *ONE_RUN, "--out", str(tmp_path)]) == 0
    meta = json.loads(run_paths(tmp_path, _spec())[2].read_text())
    assert meta["backend"] == "engine"
    assert "tamrm_server" not in meta["versions"]
    summary = _summary(tmp_path)
    assert summary["backend"] == "engine" and summary["failed"] == []
    assert "server" not in summary


def test_the_grid_with_an_address_runs_on_that_server(tmp_path):
    with tamrm.local_server() as server:
        rc = cli.main(["run", *ONE_RUN, "--out", str(tmp_path), "--address", server.address])
    assert rc == 0
    meta = json.loads(run_paths(tmp_path, _spec())[2].read_text())
    assert meta["backend"] == "server"
    summary = _summary(tmp_path)
    assert (summary["backend"], summary["server"]) == ("server", server.address)


def test_the_grid_with_an_unreachable_address_does_not_fall_back_to_the_engine(tmp_path):
    # Port 1 on localhost: nothing listens there, so every run must fail.
    rc = cli.main(["run", *ONE_RUN, "--out", str(tmp_path), "--address", "127.0.0.1:1"])
    assert rc == 1
    assert not run_paths(tmp_path, _spec())[2].exists()
    assert [f["run"] for f in _summary(tmp_path)["failed"]] == [_spec().key]


def test_the_report_counts_backends_and_reads_older_runs_as_server(tmp_path):
    runs = tmp_path / "runs"
    specs = make_specs("quick", seeds=2, experiments=["maze"], variants=["clean"])
    for spec in specs:
        write_run(runs, spec, [50] * spec.budget.episodes)  # no "backend": older runs
    # One run redone on the engine.
    meta_path = run_paths(runs, specs[0])[2]
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "backend": "engine"}))
    assert sorted(r.backend for r in load_runs(runs)) == ["engine"] + ["server"] * 7
    out = tmp_path / "reproduction.md"
    write_report(runs, out, tmp_path / "plots")
    text = out.read_text()
    how = text.split("## How this was run")[1]
    assert "1 run on the embedded engine" in how and "7 runs on a tamrm server" in how
    cost_row = next(line for line in how.splitlines() if line.startswith("| Maze | clean"))
    assert "| engine 1, server 7 |" in cost_row
    assert "gRPC round trip to the server;" not in text
