"""tamrm-trial end to end: real SB3 learners on real gymnasium envs, the real CLI.

Runs are kept tiny (a few thousand timesteps); what is asserted is the harness: paired
seeds, determinism, the null arm's identity with plain, resume, failures, bad input,
the report's files, and the server backend's identity with the engine.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("scipy")

from tamrm.trial.cli import main
from tamrm.trial.run import run_one
from tamrm.trial.settings import TrialSettings

TESTS = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def _tests_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """Workers (spawned) import ``trial_envs`` from here too."""
    path = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", str(TESTS) + (os.pathsep + path if path else ""))
    if str(TESTS) not in sys.path:
        monkeypatch.syspath_prepend(str(TESTS))


def _records(out: Path) -> dict[str, dict]:
    return {
        p.name.removesuffix(".json"): json.loads(p.read_text())
        for p in (out / "runs").glob("*.json")
        if not p.name.endswith(".failed.json")
    }


CARTPOLE = ["--env", "CartPole-v1", "--algo", "a2c", "--timesteps", "1500", "--no-progress"]


def test_cartpole_trial_null_is_plain_and_resume(tmp_path: Path) -> None:
    out = tmp_path / "trial"
    argv = [
        *CARTPOLE,
        "--seeds",
        "2",
        "--arms",
        "plain,null,tamrm",
        "--jobs",
        "2",
        "--out",
        str(out),
    ]
    assert main([*argv, "--min-pool-size", "1"]) == 0
    records = _records(out)
    assert sorted(records) == ["null-0", "null-1", "plain-0", "plain-1", "tamrm-0", "tamrm-1"]
    for seed in (0, 1):
        plain, null = records[f"plain-{seed}"], records[f"null-{seed}"]
        # The harness adds nothing: same episodes, same final parameters, bit for bit.
        assert plain["episodes"] == {k: null["episodes"][k] for k in plain["episodes"]}
        assert plain["policy_sha256"] == null["policy_sha256"]
        assert plain["shaping"] is None and null["shaping"]["knn_term_sum"] == 0.0
        # Scored on the env's own return: CartPole's return is its length.
        assert plain["episodes"]["return"] == [float(n) for n in plain["episodes"]["length"]]
        tamrm_run = records[f"tamrm-{seed}"]
        assert tamrm_run["shaping"]["pool_size"] > 0
        assert tamrm_run["shaping"]["knn_active_frac"] > 0
        assert tamrm_run["policy_sha256"] != plain["policy_sha256"]
    # Paired: seed 0 and seed 1 differ, every arm's seed s starts the same.
    assert records["plain-0"]["episodes"] != records["plain-1"]["episodes"]

    summary = json.loads((out / "summary.json").read_text())
    assert summary["null_identical_to_plain"] == {"0": True, "1": True}
    assert [c["arm"] for c in summary["comparisons"]] == ["tamrm"]
    assert summary["comparisons"][0]["verdict"] == "not enough seeds"
    report = (out / "report.md").read_text()
    assert "identical to `plain` in 2 of 2 seeds" in report
    assert "cannot reach p < 0.05" in report
    assert (out / "curves.png").stat().st_size > 10_000

    # Resume: a lost run is run again, alone; the others are kept as they were.
    before = (out / "runs" / "plain-0.json").read_bytes()
    (out / "runs" / "tamrm-1.json").unlink()
    assert main([*argv, "--min-pool-size", "1"]) == 2  # the dir holds a trial: --resume
    assert main([*argv, "--min-pool-size", "1", "--resume"]) == 0
    assert (out / "runs" / "plain-0.json").read_bytes() == before
    again = _records(out)["tamrm-1"]
    # Deterministic per seed: the rerun learned the same curve.
    assert again["episodes"] == records["tamrm-1"]["episodes"]
    assert again["policy_sha256"] == records["tamrm-1"]["policy_sha256"]
    # Settings that change the runs are refused on resume.
    assert main([*argv, "--min-pool-size", "2", "--resume"]) == 2
    # The report again, from the records alone.
    (out / "report.md").unlink()
    assert main(["--out", str(out), "--report-only"]) == 0
    assert "identical to `plain` in 2 of 2 seeds" in (out / "report.md").read_text()


def test_verdicts_from_many_seeds(tmp_path: Path) -> None:
    """Eight seeds of a shaping that cannot change learning (alpha = beta = 0 in the tamrm
    arm): every paired difference is 0, and the verdict is equivalence, not "helps"."""
    out = tmp_path / "same"
    argv = [
        "--env", "TamrmTest/Corridor-v0", "--env-module", "trial_envs", "--algo", "a2c",
        "--timesteps", "600", "--seeds", "8", "--jobs", "2", "--no-progress",
        "--alpha", "0", "--beta", "0", "--out", str(out),
    ]  # fmt: skip
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    (comparison,) = summary["comparisons"]
    assert comparison["tests"]["auc"]["n"] == 8
    assert comparison["tests"]["auc"]["difference"]["mean"] == 0.0
    assert comparison["verdict"] == "no difference"
    assert "no difference large enough to matter" in (out / "report.md").read_text()


def test_rerun_from_record_is_the_same(tmp_path: Path) -> None:
    """A reader reruns one run from its record and gets the same curve."""
    settings = TrialSettings(
        env="TamrmTest/Corridor-v0",
        env_modules=("trial_envs",),
        algo="ppo",
        timesteps=512,
        seeds=1,
        arms=("knn",),
        task={"min_pool_size": 1, "start_step": 0},
        hyperparams={"n_steps": 64, "batch_size": 32, "n_envs": 2},
        verdict=False,
    )
    first = run_one(settings, "knn", 3)
    again = run_one(TrialSettings.from_json(settings.to_json()), first["arm"], first["seed"])
    assert first["config"] == again["config"]
    assert first["episodes"] == again["episodes"]
    assert first["policy_sha256"] == again["policy_sha256"]
    assert first["episodes"]["knn_term"] and first["shaping"]["knn_active_frac"] > 0


def test_server_backend_equals_engine(tmp_path: Path, server) -> None:  # type: ignore[no-untyped-def]
    """Shaping through a server's local sessions learns exactly what the engine does."""
    settings = TrialSettings(
        env="CartPole-v1",
        algo="a2c",
        timesteps=800,
        seeds=1,
        arms=("tamrm",),
        task={"min_pool_size": 2},
        verdict=False,
        name="backend-test",
    )
    on_engine = run_one(settings, "tamrm", 5)
    on_server = run_one(settings.with_(server=server.address), "tamrm", 5)
    assert on_server["backend"] == "server" and on_engine["backend"] == "engine"
    assert on_server["episodes"] == on_engine["episodes"]
    assert on_server["policy_sha256"] == on_engine["policy_sha256"]


def test_failed_run_is_reported_and_others_go_on(tmp_path: Path) -> None:
    out = tmp_path / "crash"
    argv = [
        "--env", "TamrmTest/Crashing-v0", "--env-module", "trial_envs", "--algo", "a2c",
        "--timesteps", "300", "--seeds", "2", "--jobs", "1", "--no-progress", "--out", str(out),
    ]  # fmt: skip
    assert main(argv) == 0
    assert sorted(_records(out)) == ["plain-0", "tamrm-0"]
    failed = sorted(p.name for p in (out / "runs").glob("*.failed.json"))
    assert failed == ["plain-1.failed.json", "tamrm-1.failed.json"]
    report = (out / "report.md").read_text()
    assert "the test env broke on purpose" in report
    assert "2 failed" in report


def test_hyperparams_in_rl_zoo_layout(tmp_path: Path) -> None:
    from tamrm.trial.run import build_model

    path = tmp_path / "a2c.yml"
    path.write_text(
        "CartPole-v1:\n"
        "  n_envs: 4\n"
        "  n_timesteps: !!float 2e3\n"
        "  policy: 'MlpPolicy'\n"
        "  ent_coef: 0.0\n"
        "  learning_rate: lin_0.0008\n"
        '  policy_kwargs: "dict(net_arch=[16], activation_fn=nn.ReLU)"\n'
        "Other-v0:\n"
        "  n_envs: 1\n"
    )
    from tamrm.trial.cli import build_parser, settings_from_args

    args = build_parser().parse_args(
        [
            "--env",
            "CartPole-v1",
            "--algo",
            "a2c",
            "--hyperparams",
            str(path),
            "--out",
            str(tmp_path / "o"),
        ]
    )
    settings = settings_from_args(args)
    assert settings.timesteps == 2000  # n_timesteps, when --timesteps is not given
    model, _, _, close = build_model(settings, "plain", 0, None)
    try:
        import torch

        assert model.n_envs == 4 and model.ent_coef == 0.0
        assert model.lr_schedule(1.0) == pytest.approx(0.0008)
        assert model.lr_schedule(0.5) == pytest.approx(0.0004)
        layers = [
            m for m in model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)
        ]
        assert [m.out_features for m in layers] == [16]
        assert any(isinstance(m, torch.nn.ReLU) for m in model.policy.mlp_extractor.policy_net)
    finally:
        close()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--env", "CartPol-v1"], "did you mean CartPole-v1"),
        (["--env", "CartPole-v1", "--env-module", "no_such_module_here"], "No module named"),
        (["--env", "TamrmTest/Grid-v0", "--env-module", "trial_envs"], "MultiDiscrete"),
        (["--env", "Pendulum-v1", "--algo", "dqn"], "needs a Discrete action space"),
        (["--env", "CartPole-v1", "--arms", "plain,magic"], "unknown arm(s) magic"),
        (["--env", "CartPole-v1", "--k", "0"], "k"),
        (["--env", "CartPole-v1", "--pool-capacity", "5", "--min-pool-size", "9"], "min_pool_size"),
        (["--env", "CartPole-v1", "--gamma", "1.5"], "gamma"),
        (["--env", "CartPole-v1", "--seeds", "1"], "needs at least 2"),
        (["--env", "CartPole-v1", "--margin", "-3"], "--margin"),
        (["--env", "CartPole-v1", "--env-kwargs", "{bad"], "--env-kwargs: not JSON"),
    ],
)
def test_bad_input_is_refused_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    out = tmp_path / "bad"
    argv = ["--algo", "a2c", "--timesteps", "100", "--out", str(out), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("tamrm-trial: error: ") and message in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("CartPole-v1: [unclosed\n", "does not parse"),
        ("Acrobot-v1:\n  n_envs: 2\n", "no section for CartPole-v1"),
        ("CartPole-v1:\n  callback: x.Y\n", "'callback' is not supported"),
        ("CartPole-v1:\n  learning_rate: lin_fast\n", "lin_<number>"),
        ("CartPole-v1:\n  policy_kwargs: \"dict(f=__import__('os'))\"\n", "not allowed"),
        ("CartPole-v1:\n  not_an_a2c_argument: 3\n", "A2C rejects them"),
    ],
)
def test_bad_hyperparams_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    path = tmp_path / "h.yml"
    path.write_text(text)
    argv = [*CARTPOLE, "--hyperparams", str(path), "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_ctrl_c_keeps_finished_runs_and_reports(tmp_path: Path) -> None:
    out = tmp_path / "stopped"
    cmd = [
        sys.executable, "-m", "tamrm.trial", "--env", "TamrmTest/Corridor-v0",
        "--env-module", "trial_envs", "--algo", "a2c", "--timesteps", "400", "--seeds", "40",
        "--jobs", "1", "--no-progress", "--out", str(out),
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list((out / "runs").glob("*-*.json"))) < 2:
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted: --resume continues" in err
    kept = _records(out)
    assert 2 <= len(kept) < 80
    report = (out / "report.md").read_text()
    assert f"{len(kept)} of 80 runs finished" in report


@pytest.mark.parametrize("doc", ["README.md", "docs/trial.md"])
def test_the_documented_command_is_valid(doc: str, tmp_path: Path) -> None:
    """The command the docs show parses and passes every check before a run."""
    import re
    import shlex

    from tamrm.trial.cli import build_parser, check, settings_from_args

    root = TESTS.parents[2]
    (line,) = {m for m in re.findall(r"^tamrm-trial .*$", (root / doc).read_text(), re.M)}
    argv = shlex.split(line)[1:]
    args = build_parser().parse_args(argv)
    args.out = tmp_path / "out"
    check(settings_from_args(args))


def test_console_script() -> None:
    script = Path(sys.executable).with_name("tamrm-trial")
    done = subprocess.run([str(script), "--help"], capture_output=True, text=True, check=False)
    assert done.returncode == 0 and "--require-score-spread" in done.stdout
