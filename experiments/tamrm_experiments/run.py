"""One run (experiment, arm, seed) shaped by tamrm, and the grid runner.

A run trains a learner (the authors' loop, or a Stable-Baselines3 model on a
``ShapedVecEnv``) on the rewards tamrm computes, R_meta, and writes one CSV row per
finished episode. tamrm is either the embedded engine (``tamrm.Engine()``, in this
process, one per run: the default) or a server at an address (``tamrm.Client``); the two
give bit-identical rewards, the engine without a network round trip per step. The run's
JSON sidecar records which (``"backend"``: ``"engine"`` or ``"server"``; sidecars written
before the engine have no key and were ``"server"``). The CSV is written under a
temporary name and renamed, together with the sidecar, only when the run is complete: a
finished run is never redone, an interrupted one is redone from scratch.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tamrm_experiments.archive import archive_path, read_meta
from tamrm_experiments.configs import EXPERIMENTS, RunSpec

__all__ = [
    "BACKENDS",
    "CSV_FIELDS",
    "backend_of",
    "connect",
    "is_complete",
    "run_grid",
    "run_one",
    "run_paths",
    "versions",
]

CSV_FIELDS = [
    "episode",
    "steps",
    "env_return",
    "shaped_return",
    "knn_sum",
    "potential_sum",
    "knn_active_steps",
    "terminated",
    "truncated",
    "success",
    "score",
    "task_phase",
    "pool_version",
    "total_steps",
    "wall_time",
]

REPO = Path(__file__).resolve().parents[2]

#: Where a run's shaping is computed (its sidecar's ``"backend"``): the embedded engine,
#: in process, or a tamrm server over gRPC.
BACKENDS = ("engine", "server")


def backend_of(address: str | None) -> str:
    """The backend of a run given its server address: ``None`` is the embedded engine."""
    return "engine" if address is None else "server"


def connect(address: str | None) -> Any:
    """A new ``tamrm.Engine()`` (in memory) if ``address`` is None, else a ``tamrm.Client``.

    Both have the same methods (create_task, get_task, delete_task, session, ...) and
    give the same rewards; the engine has no network, so no timeouts."""
    import tamrm

    return tamrm.Engine() if address is None else tamrm.Client(address)


def run_paths(out: Path, spec: RunSpec) -> tuple[Path, Path, Path]:
    """Return (csv, partial csv, json sidecar) paths of ``spec`` under ``out``."""
    stem = out / spec.experiment / spec.variant / spec.arm / f"seed{spec.seed}"
    return stem.with_suffix(".csv"), stem.with_suffix(".csv.partial"), stem.with_suffix(".json")


def is_complete(out: Path, spec: RunSpec, archive: Path | None = None) -> bool:
    """Whether ``spec`` already has a finished run with the same settings under ``out``
    (CSV + sidecar) or, if given, in ``archive`` (the committed runs, one record each)."""
    csv_path, _, meta_path = run_paths(out, spec)
    same_spec = json.loads(json.dumps(spec.to_dict()))
    if archive is not None:
        record = archive_path(archive, meta_path.relative_to(out))
        if record.is_file() and read_meta(record).get("spec") == same_spec:
            return True
    if not (csv_path.is_file() and meta_path.is_file()):
        return False
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError):
        return False
    return bool(meta.get("complete")) and meta.get("spec") == same_spec


def _git_rev() -> str:
    try:
        rev = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(REPO), "status", "--porcelain", "--", "src", "proto", "clients"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


def versions(backend: str = "server") -> dict[str, str]:
    """Versions of everything that shapes the numbers.

    ``backend``: ``"server"`` records the local server binary (``tamrm_server``,
    ``tamrm_server_sha256``); ``"engine"`` the client's native extension, which embeds
    the engine (``tamrm_engine_sha256``)."""
    import gymnasium
    import stable_baselines3
    import tamrm
    import torch

    out = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "gymnasium": gymnasium.__version__,
        "tamrm_client": tamrm.__version__,
        "tamrm_git": _git_rev(),
        "cpu_count": str(os.cpu_count()),
    }
    if backend == "engine":
        try:
            from tamrm import _native

            native = Path(str(_native.__file__))
            out["tamrm_engine_sha256"] = hashlib.sha256(native.read_bytes()).hexdigest()[:16]
        except Exception:  # informational only
            out["tamrm_engine_sha256"] = "unknown"
        return out
    try:
        binary = tamrm.find_binary()
        out["tamrm_server"] = subprocess.run(
            [str(binary), "--version"], capture_output=True, text=True, timeout=10
        ).stdout.strip()
        out["tamrm_server_sha256"] = hashlib.sha256(binary.read_bytes()).hexdigest()[:16]
    except Exception:  # informational only
        out["tamrm_server"] = "unknown"
    return out


# -- environments ----------------------------------------------------------------------


def make_env(spec: RunSpec) -> Callable[[], Any]:
    """Return a factory of the run's (single) environment."""
    from tamrm_experiments import envs

    exp = EXPERIMENTS[spec.experiment]
    cap = spec.budget.max_episode_steps
    if exp.env == "cartpole":
        return envs.make_cartpole
    if exp.env == "mountaincar":
        return lambda: envs.make_mountain_car(cap)
    if exp.env == "maze":
        return lambda: envs.make_maze(cap, spec.budget.switch_after)
    if exp.env == "maze_onehot":
        return lambda: envs.make_maze_onehot(cap, spec.budget.switch_after)
    raise ValueError(f"unknown env {exp.env!r}")


# -- one run ---------------------------------------------------------------------------


@dataclass
class _Episode:
    steps: int = 0
    env_return: float = 0.0
    shaped_return: float = 0.0
    knn_sum: float = 0.0
    potential_sum: float = 0.0
    knn_active_steps: int = 0


def _make_callback(
    spec: RunSpec,
    writer: Any,
    fh: Any,
    progress: Callable[[int], None],
    on_episode: Callable[[int], None],
) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    budget = spec.budget
    success_is_truncation = EXPERIMENTS[spec.experiment].env == "cartpole"

    class EpisodeRecorder(BaseCallback):  # type: ignore[misc]
        """Writes one row per finished episode; stops at the episode or step budget."""

        def __init__(self) -> None:
            super().__init__()
            self.episodes = 0
            self.total_steps = 0
            self.phase = 0
            self.start = time.monotonic()
            self.cur = _Episode()
            self.stopped_by_steps = False

        def _on_step(self) -> bool:
            infos = self.locals["infos"]
            dones = self.locals["dones"]
            rewards = self.locals["rewards"]
            for i, info in enumerate(infos):
                self.total_steps += 1
                ep = self.cur
                ep.steps += 1
                ep.env_return += float(info.get("original_reward", 0.0))
                ep.shaped_return += float(rewards[i])
                ep.knn_sum += float(info.get("knn_reward", 0.0))
                ep.potential_sum += float(info.get("potential", 0.0))
                ep.knn_active_steps += int(bool(info.get("knn_active", False)))
                if not dones[i]:
                    continue
                truncated = bool(info.get("TimeLimit.truncated", False))
                self.episodes += 1
                writer.writerow(
                    {
                        "episode": self.episodes,
                        "steps": ep.steps,
                        "env_return": ep.env_return,
                        "shaped_return": round(ep.shaped_return, 6),
                        "knn_sum": round(ep.knn_sum, 6),
                        "potential_sum": round(ep.potential_sum, 6),
                        "knn_active_steps": ep.knn_active_steps,
                        "terminated": int(not truncated),
                        "truncated": int(truncated),
                        # Cart pole: kept up for the whole episode; elsewhere: reached the goal.
                        "success": int(truncated if success_is_truncation else not truncated),
                        "score": info.get("episode_score", ep.env_return),
                        "task_phase": self.phase,
                        "pool_version": info.get("pool_version", 0),
                        "total_steps": self.total_steps,
                        "wall_time": round(time.monotonic() - self.start, 3),
                    }
                )
                fh.flush()
                self.cur = _Episode()
                progress(1)
                if budget.switch_after is not None and self.episodes == budget.switch_after:
                    self.phase += 1
                    on_episode(self.episodes)
            if self.episodes >= budget.episodes:
                return False
            if self.total_steps >= budget.max_total_steps:
                self.stopped_by_steps = True
                return False
            return True

    return EpisodeRecorder()


def _next_task(
    client: Any, base_id: str, task_ids: list[str], num_actions: int, cfg: dict[str, Any]
) -> str:
    """Create the run's next task (a fresh pool: the modified maze's start moved, paper
    §IV-B), record it in ``task_ids`` and return its id. Called between episodes, so no
    episode of the previous task's session is in progress."""
    new_id = f"{base_id}/p{len(task_ids)}"
    _create_task(client, new_id, num_actions, cfg)
    task_ids.append(new_id)
    return new_id


def _create_task(client: Any, task_id: str, num_actions: int, cfg: dict[str, Any]) -> bool:
    """Create the task; return whether the server applies ``gate_potential`` itself.

    A client or server without SPEC v1.1's ``gate_potential`` gets the other settings;
    the caller then gates on its side (authors' loop) or fails (SB3 loop)."""
    cfg = dict(cfg)
    gate = bool(cfg.pop("gate_potential", False))
    try:
        task = client.create_task(task_id, num_actions=num_actions, gate_potential=gate, **cfg)
    except TypeError:  # a client without the keyword
        client.create_task(task_id, num_actions=num_actions, **cfg)
        return False
    # A server without field 11 ignores it: its resolved config then says false.
    return bool(getattr(task.config, "gate_potential", None) == gate)


def _sb3_kwargs(algo_kwargs: dict[str, Any], budget: Any) -> dict[str, Any]:
    """SB3 keyword arguments: ``exploration_steps`` becomes SB3's fraction of the run."""
    # SB3 mutates policy_kwargs (A2C adds its optimizer class): pass a copy.
    kwargs = copy.deepcopy(algo_kwargs)
    steps = kwargs.pop("exploration_steps", None)
    if steps is not None:
        kwargs["exploration_fraction"] = min(1.0, steps / (budget.max_total_steps + 1))
    return kwargs


def run_one(
    spec: RunSpec,
    address: str | None,
    out: Path,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Run ``spec``; write its CSV and JSON under ``out``.

    ``address``: ``None`` shapes on a new embedded engine of its own (``tamrm.Engine()``),
    else on the server at ``address``. Returns the JSON sidecar's content.
    """
    import torch

    torch.set_num_threads(1)
    progress = progress or (lambda _n: None)
    exp = EXPERIMENTS[spec.experiment]
    task_cfg = spec.task_config()
    csv_path, partial, meta_path = run_paths(out, spec)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    for stale in (csv_path, meta_path):
        stale.unlink(missing_ok=True)

    base_id = f"{spec.key.replace('/seed', '/s')}/{uuid.uuid4().hex[:12]}"
    task_ids = [base_id]
    started = time.time()
    t0 = time.monotonic()
    n_actions = _num_actions(exp.env)
    with connect(address) as client, open(partial, "w", newline="") as fh:
        gate_on_server = _create_task(client, base_id, n_actions, task_cfg)
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        writer.writeheader()
        if spec.fidelity == "authors":
            from tamrm_experiments.authors import train_authors

            def record(row: dict[str, Any]) -> None:
                writer.writerow({**row, "wall_time": round(time.monotonic() - t0, 3)})
                fh.flush()
                progress(1)

            sessions = [client.session(base_id, 1)]

            def new_task() -> Any:
                new_id = _next_task(client, base_id, task_ids, n_actions, task_cfg)
                sessions[-1].close()
                sessions.append(client.session(new_id, 1))
                return sessions[-1]

            try:
                totals = train_authors(
                    spec, sessions[0], record, gate_on_server, switch_task=new_task
                )
            finally:
                sessions[-1].close()
            episodes, total_steps = totals["episodes"], totals["total_steps"]
        else:
            if task_cfg.get("gate_potential") and not gate_on_server:
                raise RuntimeError("this server or client has no gate_potential (SPEC v1.1)")
            episodes, total_steps = _run_sb3(
                spec, client, base_id, task_ids, task_cfg, writer, fh, progress
            )
        final_pools = {}
        for tid in task_ids:
            task = client.get_task(tid)
            final_pools[tid] = {
                "pool_size": task.stats.pool_size,
                "pool_version": task.stats.pool_version,
                "best_score": task.stats.best_score,
                "worst_score": task.stats.worst_score,
                "min_length": task.stats.min_length,
                "episodes_completed": task.stats.episodes_completed,
                "steps_shaped": task.stats.steps_shaped,
            }
            client.delete_task(tid)
    wall = time.monotonic() - t0
    censored = episodes < spec.budget.episodes
    meta = {
        "spec": spec.to_dict(),
        "complete": True,
        "episodes": episodes,
        "total_steps": total_steps,
        "censored": censored,
        "gate_potential_on_server": gate_on_server,
        "backend": backend_of(address),
        "wall_time_s": round(wall, 2),
        "steps_per_s": round(total_steps / wall, 1) if wall > 0 else None,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
        "task_ids": task_ids,
        "final_pools": final_pools,
        "versions": versions(backend_of(address)),
    }
    os.replace(partial, csv_path)
    tmp_meta = meta_path.with_suffix(".json.tmp")
    tmp_meta.write_text(json.dumps(meta, indent=1))
    os.replace(tmp_meta, meta_path)
    return meta


def _run_sb3(
    spec: RunSpec,
    client: Any,
    base_id: str,
    task_ids: list[str],
    task_cfg: dict[str, Any],
    writer: Any,
    fh: Any,
    progress: Callable[[int], None],
) -> tuple[int, int]:
    """The clean fidelity: an SB3 model on a ``ShapedVecEnv``; returns (episodes, steps)."""
    from stable_baselines3 import A2C, DQN
    from stable_baselines3.common.vec_env import DummyVecEnv
    from tamrm.sb3 import ShapedVecEnv

    exp = EXPERIMENTS[spec.experiment]
    shaped = ShapedVecEnv(
        DummyVecEnv([make_env(spec)]),
        client.session(base_id, 1),
        # The maze's score (100 / steps on success) comes with the episode's last info.
        score_key="episode_score" if exp.score_from_info else None,
    )

    def switch_task(_episode: int) -> None:
        new_id = _next_task(client, base_id, task_ids, _num_actions(exp.env), task_cfg)
        shaped.session.close()
        shaped.session = client.session(new_id, 1)

    algo = {"a2c": A2C, "dqn": DQN}[exp.algo]
    # SB3 makes a new (here empty) log dir under the temp dir at every learn() unless
    # $SB3_LOGDIR names one: a grid would leave one per run.
    os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "tamrm-sb3-logs"))
    kwargs = _sb3_kwargs(exp.algo_kwargs, spec.budget)
    model = algo("MlpPolicy", shaped, seed=spec.seed, device="cpu", **kwargs)
    shaped.bind_model(model)
    callback = _make_callback(spec, writer, fh, progress, switch_task)
    model.learn(total_timesteps=spec.budget.max_total_steps + 1, callback=callback)
    shaped.session.close()
    return callback.episodes, callback.total_steps


def _num_actions(env: str) -> int:
    return {"cartpole": 2, "mountaincar": 3, "maze": 4, "maze_onehot": 4}[env]


# -- the grid --------------------------------------------------------------------------

_QUEUE: Any = None


def _worker_init(queue: Any) -> None:
    global _QUEUE
    _QUEUE = queue
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


def _worker_run(spec: RunSpec, address: str | None, out: str) -> dict[str, Any]:
    queue = _QUEUE

    def progress(n: int) -> None:
        if queue is not None:
            queue.put((spec.key, n))

    if is_complete(Path(out), spec):  # finished meanwhile by another invocation
        meta: dict[str, Any] = json.loads(run_paths(Path(out), spec)[2].read_text())
        return meta
    lock = _lock(Path(out), spec)
    if lock is None:  # being run by another invocation right now
        return {"episodes": 0, "skipped": "running elsewhere"}
    try:
        return run_one(spec, address, Path(out), progress)
    finally:
        lock.unlink(missing_ok=True)


def _lock(out: Path, spec: RunSpec) -> Path | None:
    """Take the run's lock file (several invocations may share a runs directory)."""
    path = run_paths(out, spec)[0].with_suffix(".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(path.read_text().strip() or "0")
                os.kill(pid, 0)
                return None  # its owner is alive
            except (ValueError, ProcessLookupError, FileNotFoundError):
                path.unlink(missing_ok=True)  # stale: its owner died
                continue
            except PermissionError:
                return None
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        return path
    return None


def run_grid(
    specs: list[RunSpec],
    out: Path,
    jobs: int,
    address: str | None = None,
    show_progress: bool = True,
    archive: Path | None = None,
) -> dict[str, Any]:
    """Run every spec not yet complete under ``out`` (nor in ``archive``, the committed
    runs, if given) on ``jobs`` processes.

    Each run shapes on an embedded engine of its own, or on the server at ``address`` if
    given (no server is started here). Returns a summary (runs done, skipped, failed,
    backend, wall time).
    """
    import multiprocessing as mp

    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    todo = [s for s in specs if not is_complete(out, s, archive)]
    skipped = len(specs) - len(todo)
    summary: dict[str, Any] = {
        "command": " ".join([Path(sys.executable).name, "-m", "tamrm_experiments", *sys.argv[1:]]),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "runs_total": len(specs),
        "runs_skipped_complete": skipped,
        "runs_todo": len(todo),
        "jobs": jobs,
        "backend": backend_of(address),
        "failed": [],
    }
    if address is not None:
        summary["server"] = address
    t0 = time.monotonic()
    # A start record: the report lists what a still-running invocation asked for.
    with open(out / "invocations.jsonl", "a") as fh:
        fh.write(json.dumps({**summary, "status": "started"}) + "\n")
    import signal

    def _on_term(_sig: int, _frame: Any) -> None:
        raise SystemExit(143)

    signal.signal(signal.SIGTERM, _on_term)
    try:
        if todo:
            _run_pool(todo, address, out, jobs, summary, show_progress, mp, tqdm)
    finally:
        summary["wall_time_s"] = round(time.monotonic() - t0, 1)
        summary["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        with open(out / "invocations.jsonl", "a") as fh:
            fh.write(json.dumps(summary) + "\n")
    return summary


def _run_pool(
    todo: list[RunSpec],
    address: str | None,
    out: Path,
    jobs: int,
    summary: dict[str, Any],
    show_progress: bool,
    mp: Any,
    tqdm: Any,
) -> None:
    ctx = mp.get_context("spawn")
    manager = ctx.Manager()
    queue = manager.Queue()
    total_eps = sum(s.budget.episodes for s in todo)
    disable = not show_progress
    runs_bar = tqdm(total=len(todo), desc="runs", position=0, disable=disable, unit="run")
    eps_bar = tqdm(total=total_eps, desc="episodes", position=1, disable=disable, unit="ep")
    running: dict[str, Any] = {}
    totals = {s.key: s.budget.episodes for s in todo}
    pool = ProcessPoolExecutor(
        max_workers=jobs, mp_context=ctx, initializer=_worker_init, initargs=(queue,)
    )
    interrupted = False
    try:
        futures: dict[Future[dict[str, Any]], RunSpec] = {
            pool.submit(_worker_run, s, address, str(out)): s for s in todo
        }
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            _drain(queue, eps_bar, running, totals, tqdm, disable)
            for fut in done:
                spec = futures[fut]
                bar = running.pop(spec.key, None)
                if bar is not None:
                    bar.close()
                try:
                    meta = fut.result()
                    eps_bar.update(max(0, spec.budget.episodes - meta["episodes"]))
                except Exception as exc:  # reported; the grid goes on
                    summary["failed"].append({"run": spec.key, "error": repr(exc)})
                    tqdm.write(f"FAILED {spec.key}: {exc!r}")
                runs_bar.update(1)
        _drain(queue, eps_bar, running, totals, tqdm, disable)
    except BaseException:
        # Interrupted (Ctrl-C, SIGTERM): stop the workers now; their runs stay unfinished
        # (.csv.partial) and are redone by the next invocation.
        interrupted = True
        summary["interrupted"] = True
        for proc in list(getattr(pool, "_processes", {}).values()):
            proc.terminate()
        raise
    finally:
        pool.shutdown(wait=not interrupted, cancel_futures=True)
        for bar in running.values():
            bar.close()
        eps_bar.close()
        runs_bar.close()
        manager.shutdown()


def _drain(
    queue: Any,
    eps_bar: Any,
    running: dict[str, Any],
    totals: dict[str, int],
    tqdm: Any,
    disable: bool,
) -> None:
    import queue as queue_mod

    while True:
        try:
            key, n = queue.get_nowait()
        except queue_mod.Empty:
            return
        except (EOFError, OSError):
            return
        bar = running.get(key)
        if bar is None:
            bar = tqdm(
                total=totals.get(key),
                desc=key,
                position=2 + len(running),
                leave=False,
                disable=disable,
                unit="ep",
            )
            running[key] = bar
        bar.update(n)
        eps_bar.update(n)
