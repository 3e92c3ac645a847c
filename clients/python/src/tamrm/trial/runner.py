"""A trial's runs on worker processes: written once each, resumable, with one progress bar.

Each finished run is written to ``DIR/runs/<arm>-<seed>.json`` (under a temporary name,
then renamed) by the parent process only. A run that raises is written as
``<arm>-<seed>.failed.json`` with its error, and the others go on; a later ``--resume``
tries it again. Ctrl-C (or SIGTERM) stops the workers; every finished run stays.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tamrm.trial.settings import TrialSettings, run_name

__all__ = ["RunOutcome", "load_records", "read_record", "run_trial", "runs_dir"]


def runs_dir(out: Path) -> Path:
    """Where a trial's run records are."""
    return out / "runs"


def _write_json(path: Path, data: Any) -> None:
    """Write ``data`` to ``path`` atomically (a temporary file renamed over it)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=None, separators=(",", ":")) + "\n")
    os.replace(tmp, path)


def read_record(path: Path) -> dict[str, Any] | None:
    """A run record, or ``None`` when the file is missing or not a complete record."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "episodes" in data else None


def load_records(
    out: Path, settings: TrialSettings
) -> tuple[dict[tuple[str, int], Any], dict[tuple[str, int], str]]:
    """The trial's finished runs whose config is the trial's, and its failed runs' errors."""
    records: dict[tuple[str, int], Any] = {}
    failures: dict[tuple[str, int], str] = {}
    folder = runs_dir(out)
    for arm, seed in settings.runs():
        stem = run_name(arm, seed)
        record = read_record(folder / f"{stem}.json")
        if record is not None and record.get("config") == settings.run_config(arm):
            records[(arm, seed)] = record
            continue
        try:
            failure = json.loads((folder / f"{stem}.failed.json").read_text())
            failures[(arm, seed)] = str(failure.get("error", "unknown error"))
        except (OSError, ValueError):
            pass
    return records, failures


@dataclass
class RunOutcome:
    """What :func:`run_trial` did."""

    done: list[tuple[str, int]] = field(default_factory=list)
    skipped: list[tuple[str, int]] = field(default_factory=list)
    failed: dict[tuple[str, int], str] = field(default_factory=dict)
    interrupted: bool = False
    wall_time_s: float = 0.0


_QUEUE: Any = None


def _worker_init(queue: Any) -> None:
    """A worker: one torch thread, and Ctrl-C is the parent's to handle."""
    global _QUEUE
    _QUEUE = queue
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def _worker_run(settings_json: dict[str, Any], arm: str, seed: int) -> dict[str, Any]:
    from tamrm.trial.run import run_one

    queue = _QUEUE

    def progress(steps: int) -> None:
        if queue is not None and steps > 0:
            queue.put(steps)

    return run_one(TrialSettings.from_json(settings_json), arm, seed, progress)


def _describe(record: dict[str, Any]) -> str:
    returns = record["episodes"]["return"]
    tail = returns[-max(1, len(returns) // 10) :] if returns else []
    last = sum(tail) / len(tail) if tail else float("nan")
    return (
        f"{len(returns)} episodes, last 10 % of episodes' mean return {last:.4g}, "
        f"{record['wall_time_s']:.0f} s"
    )


def run_trial(
    settings: TrialSettings,
    out: Path,
    jobs: int,
    *,
    show_progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> RunOutcome:
    """Run every run of the trial that has no record yet, on ``jobs`` processes.

    ``log`` gets one line per finished or failed run (default: stderr, through the bar).
    """
    import multiprocessing as mp

    from tqdm import tqdm  # type: ignore[import-untyped]

    folder = runs_dir(out)
    folder.mkdir(parents=True, exist_ok=True)
    records, _ = load_records(out, settings)
    todo = [run for run in settings.runs() if run not in records]
    outcome = RunOutcome(skipped=[run for run in settings.runs() if run in records])
    if not todo:
        return outcome
    t0 = time.monotonic()
    bar = tqdm(
        total=settings.timesteps * len(todo),
        unit="step",
        unit_scale=True,
        desc=f"runs 0/{len(todo)}",
        disable=not show_progress,
        dynamic_ncols=True,
    )
    write = log or (lambda line: tqdm.write(line, file=sys.stderr))
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    pool = ProcessPoolExecutor(
        max_workers=max(1, min(jobs, len(todo))),
        mp_context=ctx,
        initializer=_worker_init,
        initargs=(queue,),
    )
    previous = signal.getsignal(signal.SIGTERM)

    def on_term(_sig: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    settings_json = settings.to_json()
    try:
        futures: dict[Future[dict[str, Any]], tuple[str, int]] = {
            pool.submit(_worker_run, settings_json, arm, seed): (arm, seed) for arm, seed in todo
        }
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            _drain(queue, bar)
            for fut in finished:
                arm, seed = run = futures[fut]
                stem = run_name(arm, seed)
                try:
                    record = fut.result()
                except Exception as exc:
                    error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                    _write_json(
                        folder / f"{stem}.failed.json", {"arm": arm, "seed": seed, "error": error}
                    )
                    outcome.failed[run] = error
                    write(f"FAILED {stem}: {error}")
                else:
                    _write_json(folder / f"{stem}.json", record)
                    (folder / f"{stem}.failed.json").unlink(missing_ok=True)
                    outcome.done.append(run)
                    write(f"done {stem}: {_describe(record)}")
                bar.set_description(f"runs {len(outcome.done) + len(outcome.failed)}/{len(todo)}")
        _drain(queue, bar)
    except KeyboardInterrupt:
        outcome.interrupted = True
        for proc in list(getattr(pool, "_processes", {}).values()):
            proc.terminate()
    finally:
        signal.signal(signal.SIGTERM, previous)
        pool.shutdown(wait=not outcome.interrupted, cancel_futures=True)
        bar.close()
        outcome.wall_time_s = time.monotonic() - t0
    return outcome


def _drain(queue: Any, bar: Any) -> None:
    import queue as queue_mod

    steps = 0
    while True:
        try:
            steps += queue.get_nowait()
        except (queue_mod.Empty, EOFError, OSError):
            break
    if steps:
        bar.update(steps)
