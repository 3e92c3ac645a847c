"""Running the study's runs: each one a ``tamrm.trial`` run, written once as gzipped JSON.

A record is the trial's run record plus ``"study"``: the stage, variant, arm, settings and
seed it was run for. Records are written under a temporary name and renamed; an existing
record is never rewritten, so a grid continues across sessions and the committed records
stay as they were first written.
"""

from __future__ import annotations

import gzip
import json
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from functools import partial
from pathlib import Path
from typing import Any

from tamrm_regimes.study import (
    ALGO,
    BUDGET,
    DEFAULT_BETA,
    HYPERPARAMS,
    PILOT_BUDGET,
    RunKey,
    variant,
)

__all__ = ["key_from_json", "key_json", "read_record", "run_key", "run_keys", "settings_for"]

ENV_MODULE = "tamrm_regimes.envs"


def key_json(key: RunKey) -> dict[str, Any]:
    """A JSON-able form of a run key."""
    return {
        "stage": key.stage,
        "variant": key.variant,
        "arm": key.arm,
        "seed": key.seed,
        "config": dict(key.config),
    }


def key_from_json(data: dict[str, Any]) -> RunKey:
    """The run key of :func:`key_json`."""
    return RunKey(data["stage"], data["variant"], data["arm"], int(data["seed"]), data["config"])


def _oracle_pool(key: RunKey, capacity: int) -> tuple[tuple[tuple[int, ...], float], ...]:
    """The oracle arm's pool: half shortest paths (scored as the env scores them), half
    random walks that failed (score 0), drawn from the run's seed."""
    import numpy as np

    from tamrm_regimes.envs import MAZE_CAP, goal_return, make_maze, shortest_paths

    paths = shortest_paths()
    best = paths[: max(1, capacity // 2)]
    out = [(tuple(p), goal_return(len(p), MAZE_CAP)) for p in best]
    rng = np.random.default_rng(key.seed)
    env = make_maze(**variant(key.variant).kwargs)
    while len(out) < capacity:
        env.reset(seed=int(rng.integers(2**31)))
        actions: list[int] = []
        done = False
        reward: Any = 0.0
        while not done:
            action = int(rng.integers(4))
            _, reward, terminated, truncated, _ = env.step(action)
            actions.append(action)
            done = terminated or truncated
        if reward == 0.0:
            out.append((tuple(actions), 0.0))
    return tuple(out)


def settings_for(key: RunKey, timesteps: int | None = None) -> tuple[Any, str, Any]:
    """The trial settings, trial arm and hooks that run ``key``."""
    from tamrm.trial.run import RunHooks
    from tamrm.trial.settings import TrialSettings

    from tamrm_regimes.sil import sil_class

    var = variant(key.variant)
    config = dict(key.config)
    hooks = RunHooks()
    task: dict[str, Any] = {}
    arm = key.arm
    if arm == "plain":
        pass
    elif arm == "pbrs":
        task = {"beta": DEFAULT_BETA}
    elif arm in ("knn", "tamrm"):
        task = {**config, "beta": DEFAULT_BETA}
    elif arm == "oracle":
        task = dict(config)
        hooks = RunHooks(prefill=_oracle_pool(key, int(config["pool_capacity"])), label="oracle")
        arm = "knn"
    elif arm == "sil":
        hooks = RunHooks(model_class=partial(sil_class(ALGO), **config), label="sil")
        arm = "plain"
    else:
        raise ValueError(f"unknown study arm {key.arm!r}")
    settings = TrialSettings(
        env=var.env,
        env_modules=(ENV_MODULE,),
        env_kwargs=var.env_kwargs(key.seed),
        algo=ALGO,
        timesteps=timesteps or (PILOT_BUDGET if key.stage == "pilot" else BUDGET)[var.family],
        seeds=1,
        seed0=key.seed,
        arms=(arm,),
        task=task,
        hyperparams=HYPERPARAMS,
        verdict=False,
        name=f"regimes-{key.stage}-{key.variant}",
    )
    return settings, arm, hooks


def run_key(key_data: dict[str, Any], timesteps: int | None = None) -> dict[str, Any]:
    """Run one study run (in a worker); returns its record."""
    from tamrm.trial.run import run_one

    key = key_from_json(key_data)
    settings, arm, hooks = settings_for(key, timesteps)
    record = run_one(settings, arm, key.seed, hooks=hooks)
    record["study"] = {**key_data, "timesteps": settings.timesteps}
    return record


def rerun(record: dict[str, Any]) -> dict[str, Any]:
    """Run a recorded run again from the settings its record holds (not today's grid)."""
    from tamrm.trial.run import run_one
    from tamrm.trial.settings import TrialSettings

    key = key_from_json(record["study"])
    _, arm, hooks = settings_for(key, record["study"]["timesteps"])
    c = record["config"]
    settings = TrialSettings(
        env=c["env"],
        env_modules=tuple(c["env_modules"]),
        env_kwargs=c["env_kwargs"],
        algo=c["algo"],
        timesteps=c["timesteps"],
        seeds=1,
        seed0=key.seed,
        arms=(c["arm"],),
        task=c["task"] or {},
        hyperparams=c["hyperparams"],
        verdict=False,
    )
    return run_one(settings, arm, key.seed, hooks=hooks)


def read_record(path: Path) -> dict[str, Any] | None:
    """A record, or ``None`` if it is missing or unreadable."""
    try:
        with gzip.open(path, "rt") as fh:
            data: dict[str, Any] = json.load(fh)
    except (OSError, ValueError, EOFError):
        return None
    return data


def _write(path: Path, record: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    # mtime=0: the same record gives the same bytes.
    with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as fh:
        fh.write(json.dumps(record, separators=(",", ":")).encode())
    os.replace(tmp, path)


def _init() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def run_keys(
    keys: Sequence[RunKey],
    runs_dir: Path,
    jobs: int,
    timesteps: int | None = None,
    log: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True),
) -> dict[str, int]:
    """Run every key without a record under ``runs_dir``; returns counts."""
    import multiprocessing as mp

    todo = [k for k in keys if not (runs_dir / k.path).is_file()]
    counts = {"done": 0, "failed": 0, "skipped": len(keys) - len(todo)}
    if not todo:
        return counts
    started = time.monotonic()
    pool = ProcessPoolExecutor(
        max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=_init
    )
    try:
        futures: dict[Future[dict[str, Any]], RunKey] = {
            pool.submit(run_key, key_json(k), timesteps): k for k in todo
        }
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                key = futures[fut]
                path = runs_dir / key.path
                try:
                    record = fut.result()
                except Exception as exc:
                    counts["failed"] += 1
                    error = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
                    failed = path.with_name(path.name.replace(".json.gz", ".failed.txt"))
                    failed.parent.mkdir(parents=True, exist_ok=True)
                    failed.write_text(error)
                    log(f"FAILED {key.path}: {exc!r}")
                    continue
                _write(path, record)
                counts["done"] += 1
                elapsed = time.monotonic() - started
                left = len(todo) - counts["done"] - counts["failed"]
                eta = elapsed / (counts["done"] + counts["failed"]) * left
                returns = record["episodes"]["return"]
                tail = returns[-50:]
                log(
                    f"done {key.path} ({record['wall_time_s']:.0f} s, last 50 episodes' mean "
                    f"return {sum(tail) / max(1, len(tail)):.3f}); {left} left, "
                    f"ETA {eta / 60:.0f} min"
                )
    except KeyboardInterrupt:
        for proc in list(getattr(pool, "_processes", {}).values()):
            proc.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return counts
