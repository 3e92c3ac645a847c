"""``tamrm-trial`` (``python -m tamrm.trial``): does shaping help on my task?

Every input is checked before any run starts; a mistake is one line on stderr and exit
status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import json
import math
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tamrm._types import CONFIG_FIELDS, TaskConfig
from tamrm.trial.settings import ALGOS, ARMS, DEFAULT_ARMS, Margin, TrialSettings

__all__ = ["TrialError", "build_parser", "main", "settings_from_args"]

#: Config fields the env's action space sets.
_FROM_ENV = ("num_actions", "action_dim")


class TrialError(Exception):
    """An input the trial cannot run with; the message says which and why."""


def _field_help() -> dict[str, str]:
    """Each ``TaskConfig`` field's description, from the class's docstring."""
    doc = TaskConfig.__doc__ or ""
    helps: dict[str, str] = {}
    current = None
    for line in doc.splitlines():
        match = re.match(r"\s{8}(\w+): (.*)", line)
        if match and match.group(1) in CONFIG_FIELDS:
            current = match.group(1)
            helps[current] = match.group(2).strip()
        elif current and re.match(r"\s{12}\S", line):
            helps[current] += " " + line.strip()
        else:
            current = None
    return helps


def _config_types() -> dict[str, type]:
    """Each ``TaskConfig`` field's Python type (its annotations are strings)."""
    kinds = {"int": int, "float": float, "bool": bool}
    return {f.name: kinds[str(f.type)] for f in dataclasses.fields(TaskConfig)}


def build_parser() -> argparse.ArgumentParser:
    """The command line (every ``TaskConfig`` field is an option of its own)."""
    p = argparse.ArgumentParser(
        prog="tamrm-trial",
        description=(
            "An honest A/B of reward shaping on a gymnasium environment: paired seeds, "
            "the environment's own return, curves, paired tests and a verdict per arm."
        ),
        epilog="docs/trial.md explains the report and what a trial costs.",
    )
    p.add_argument("--env", help="a registered gymnasium id (required unless --report-only)")
    p.add_argument(
        "--env-module",
        action="append",
        default=[],
        metavar="MODULE",
        help="import MODULE first (it registers the env); repeatable",
    )
    p.add_argument(
        "--env-kwargs", default="{}", metavar="JSON", help="keyword arguments of gymnasium.make"
    )
    p.add_argument(
        "--algo", choices=ALGOS, help="Stable-Baselines3 algorithm (required unless --report-only)"
    )
    p.add_argument(
        "--timesteps",
        type=int,
        help="environment steps per run (default: the hyperparameter file's n_timesteps)",
    )
    p.add_argument("--seeds", type=int, default=5, help="paired seeds per arm [5]")
    p.add_argument("--seed0", type=int, default=0, help="the first seed [0]")
    p.add_argument(
        "--arms",
        default=",".join(DEFAULT_ARMS),
        help=f"comma-separated, of {', '.join(ARMS)} [{','.join(DEFAULT_ARMS)}]",
    )
    p.add_argument("--out", required=True, type=Path, help="the trial's directory")
    p.add_argument("--jobs", type=int, default=None, help="worker processes [the CPUs]")
    p.add_argument(
        "--hyperparams", type=Path, metavar="FILE", help="YAML or JSON, rl-zoo3's layout"
    )
    p.add_argument("--threshold", type=float, help="also time the first crossing of this return")
    p.add_argument(
        "--margin",
        default="10%",
        help="equivalence margin: a share of plain's AUC (10%%) or a return (5.0) [10%%]",
    )
    p.add_argument(
        "--no-verdict",
        dest="verdict",
        action="store_false",
        help="curves and metrics only (allows --seeds 1)",
    )
    p.add_argument("--server", metavar="ADDR", help="shape through this server, local sessions")
    p.add_argument("--name", help="the trial's name (its task ids on a server) [the --out dir's]")
    p.add_argument("--resume", action="store_true", help="continue the trial in --out")
    p.add_argument(
        "--report-only", action="store_true", help="write the report from --out's runs, run none"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    shaping = p.add_argument_group(
        "shaping (TaskConfig, SPEC §1.1; unset: the defaults; alpha and beta are zeroed per arm)"
    )
    helps = _field_help()
    for name, kind in _config_types().items():
        if name in _FROM_ENV:
            continue
        flag = "--" + name.replace("_", "-")
        if kind is bool:
            shaping.add_argument(
                flag,
                dest=name,
                action=argparse.BooleanOptionalAction,
                default=None,
                help=helps.get(name),
            )
        else:
            shaping.add_argument(flag, dest=name, type=kind, default=None, help=helps.get(name))
    return p


def _check_env(settings: TrialSettings) -> dict[str, Any]:
    """Import the env's modules, make it once; return the task's action space keywords."""
    import gymnasium as gym

    from tamrm.trial.run import action_space_config, import_env_modules

    try:
        import_env_modules(settings.env_modules)
    except ImportError as exc:
        raise TrialError(f"--env-module: {exc}") from None
    if settings.env not in gym.registry:
        close = difflib.get_close_matches(settings.env, list(gym.registry), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise TrialError(
            f"--env {settings.env}: not a registered gymnasium id{hint}; --env-module M "
            "imports the module that registers it"
        )
    try:
        env: Any = gym.make(settings.env, **dict(settings.env_kwargs))
    except Exception as exc:
        raise TrialError(f"--env {settings.env}: gymnasium.make failed: {exc}") from None
    try:
        space = env.action_space
        try:
            keywords = action_space_config(space)
        except ValueError as exc:
            raise TrialError(f"--env {settings.env}: {exc}") from None
        if settings.algo == "dqn" and "num_actions" not in keywords:
            raise TrialError(
                f"--algo dqn needs a Discrete action space; {settings.env} has {space}"
            )
    finally:
        env.close()
    return keywords


def _check_task(settings: TrialSettings, keywords: dict[str, Any]) -> None:
    """Every shaping arm's config, created on a throwaway engine: SPEC's own checks."""
    import tamrm
    from tamrm.trial.settings import arm_task_config

    with tamrm.Engine() as engine:
        for i, arm in enumerate(settings.arms):
            config = arm_task_config(arm, settings.task)
            if config is None:
                continue
            try:
                engine.create_task(f"check-{i}", **keywords, **config)
            except tamrm.InvalidArgument as exc:
                raise TrialError(f"shaping settings of arm {arm}: {exc}") from None


def _check_model(settings: TrialSettings) -> None:
    """Build the plain model once: the hyperparameters must be the algorithm's."""
    from tamrm.trial.hyperparams import HyperparamsError
    from tamrm.trial.run import build_model

    try:
        model, _, _, close = build_model(settings, "plain", settings.seed0, None)
    except HyperparamsError as exc:
        raise TrialError(f"--hyperparams: {exc}") from None
    except (TypeError, ValueError, AssertionError) as exc:
        raise TrialError(f"--hyperparams: {settings.algo.upper()} rejects them: {exc}") from None
    del model
    close()


def _check_server(address: str) -> None:
    import tamrm

    try:
        with tamrm.Client(address) as client:
            client.wait_ready(timeout=10.0)
    except Exception as exc:
        raise TrialError(f"--server {address}: not reachable: {exc}") from None


def settings_from_args(args: argparse.Namespace) -> TrialSettings:
    """The trial's settings from the parsed command line, every input checked.

    Raises:
        TrialError: An input the trial cannot run with.
    """
    from tamrm.trial.hyperparams import HyperparamsError, load_section

    arms = tuple(a.strip() for a in args.arms.split(",") if a.strip())
    unknown = [a for a in arms if a not in ARMS]
    if unknown or not arms:
        raise TrialError(
            f"--arms {args.arms}: unknown arm(s) {', '.join(unknown) or '(none)'}; the arms "
            f"are {', '.join(ARMS)}"
        )
    if len(set(arms)) != len(arms):
        raise TrialError(f"--arms {args.arms}: an arm is named twice")
    arms = tuple(sorted(arms, key=ARMS.index))
    if args.seeds < 1:
        raise TrialError(f"--seeds {args.seeds}: at least 1")
    if args.seeds < 2 and args.verdict:
        raise TrialError(
            f"--seeds {args.seeds}: a verdict compares paired seeds and needs at least 2 "
            "(6 for the signed-rank test to be able to reach p < 0.05); --no-verdict for "
            "curves only"
        )
    if args.jobs is not None and args.jobs < 1:
        raise TrialError(f"--jobs {args.jobs}: at least 1")
    try:
        env_kwargs = json.loads(args.env_kwargs)
    except ValueError as exc:
        raise TrialError(f"--env-kwargs: not JSON: {exc}") from None
    if not isinstance(env_kwargs, dict):
        raise TrialError("--env-kwargs: a JSON object of keyword arguments")
    try:
        margin = Margin.parse(args.margin)
    except ValueError as exc:
        raise TrialError(str(exc)) from None
    if args.threshold is not None and not math.isfinite(args.threshold):
        raise TrialError(f"--threshold {args.threshold}: a finite return")
    hyperparams: dict[str, Any] = {}
    if args.hyperparams is not None:
        try:
            hyperparams = load_section(args.hyperparams, args.env)
        except HyperparamsError as exc:
            raise TrialError(str(exc)) from None
    timesteps = args.timesteps if args.timesteps is not None else hyperparams.get("n_timesteps")
    hyperparams.pop("n_timesteps", None)
    if timesteps is None:
        raise TrialError("--timesteps: give the steps per run (no n_timesteps in --hyperparams)")
    if int(timesteps) != timesteps or timesteps < 1:
        raise TrialError(f"--timesteps {timesteps}: a positive integer")
    task = {
        name: getattr(args, name)
        for name in CONFIG_FIELDS
        if name not in _FROM_ENV and getattr(args, name, None) is not None
    }
    name = args.name or args.out.resolve().name
    return TrialSettings(
        env=args.env,
        algo=args.algo,
        timesteps=int(timesteps),
        seeds=args.seeds,
        arms=arms,
        env_modules=tuple(args.env_module),
        env_kwargs=env_kwargs,
        seed0=args.seed0,
        task=task,
        hyperparams=hyperparams,
        hyperparams_file=str(args.hyperparams) if args.hyperparams else None,
        threshold=args.threshold,
        margin=margin,
        verdict=args.verdict,
        server=args.server,
        name=name,
    )


def check(settings: TrialSettings) -> None:
    """Every check that needs the env, tamrm or Stable-Baselines3 (before any run).

    Raises:
        TrialError: The first problem found.
    """
    keywords = _check_env(settings)
    _check_task(settings, keywords)
    _check_model(settings)
    if settings.server is not None:
        _check_server(settings.server)


def _trial_file(out: Path) -> Path:
    return out / "trial.json"


def _prepare_out(settings: TrialSettings, out: Path, resume: bool) -> None:
    """Record the settings in ``out``; refuse another trial's directory."""
    path = _trial_file(out)
    if path.is_file():
        if not resume:
            raise TrialError(
                f"--out {out}: holds a trial already; --resume continues it, or choose "
                "another directory"
            )
        previous = TrialSettings.from_json(json.loads(path.read_text()))
        for arm in set(previous.arms) & set(settings.arms):
            if previous.run_config(arm) != settings.run_config(arm):
                changed = [
                    k
                    for k, v in settings.run_config(arm).items()
                    if previous.run_config(arm).get(k) != v
                ]
                raise TrialError(
                    f"--resume: the runs in {out} were made with other settings "
                    f"({', '.join(changed)} differ); choose another --out"
                )
    elif out.exists() and any(out.iterdir()):
        raise TrialError(f"--out {out}: not empty and not a trial's directory")
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings.to_json(), indent=1) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.report_only and (args.env is None or args.algo is None):
        parser.error("--env and --algo are required (unless --report-only)")
    try:
        if args.report_only:
            path = _trial_file(args.out)
            if not path.is_file():
                raise TrialError(f"--out {args.out}: no trial.json, nothing to report")
            settings = TrialSettings.from_json(json.loads(path.read_text()))
        else:
            settings = settings_from_args(args)
            check(settings)
            _prepare_out(settings, args.out, args.resume)
    except TrialError as exc:
        print(f"tamrm-trial: error: {exc}", file=sys.stderr)
        return 2
    interrupted = False
    if not args.report_only:
        from tamrm.trial.runner import run_trial

        if settings.verdict and settings.seeds < 6:
            print(
                f"tamrm-trial: note: with {settings.seeds} seeds the signed-rank test cannot reach "
                "p < 0.05; the verdict will be 'not enough seeds' unless more are run",
                file=sys.stderr,
            )
        jobs = args.jobs or len(os.sched_getaffinity(0))
        outcome = run_trial(
            settings, args.out, jobs, show_progress=not args.no_progress and sys.stderr.isatty()
        )
        interrupted = outcome.interrupted
        print(
            f"tamrm-trial: {len(outcome.done)} runs done, {len(outcome.skipped)} already there, "
            f"{len(outcome.failed)} failed in {outcome.wall_time_s:.0f} s"
            + ("; interrupted: --resume continues" if interrupted else ""),
            file=sys.stderr,
        )
    from tamrm.trial.report import Report

    report = Report(settings, args.out)
    report.write()
    print(f"tamrm-trial: report in {args.out / 'report.md'}", file=sys.stderr)
    for c in report.comparisons if settings.verdict else []:
        print(f"  {c.headline} {c.sentence}")
    return 130 if interrupted else 0
