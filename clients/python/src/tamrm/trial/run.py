"""One run of a trial: one arm, one seed, one Stable-Baselines3 learner.

The env is built as ``make_vec_env`` builds it, a ``Monitor`` in every sub-environment,
so the returns recorded are the environment's own; any ``VecNormalize`` or
``VecFrameStack`` of the hyperparameters comes next, and the shaping wrapper
(``tamrm.sb3.ShapedVecEnv``) is outermost, so the model's value estimates are computed
on the observations the model sees. The ``plain`` arm has no shaping wrapper and no task.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from tamrm._errors import TaskNotFound
from tamrm.trial.hyperparams import Hyperparams, resolve
from tamrm.trial.settings import TrialSettings, arm_task_config, task_id

__all__ = [
    "RECORD_FORMAT",
    "RunHooks",
    "action_space_config",
    "build_model",
    "import_env_modules",
    "run_one",
    "versions",
]

#: The version of a run record's layout.
RECORD_FORMAT = 1
#: The info key carrying an episode's unshaped return to the shaping wrapper as its
#: score (used when rewards are normalised below the wrapper).
_SCORE_KEY = "tamrm_trial_return"
#: How often a run reports its progress, in environment steps.
_PROGRESS_EVERY = 2048


@dataclass(frozen=True)
class RunHooks:
    """What a study may change in a run beyond a trial's settings.

    The command line has none of them.

    Attributes:
        model_class: Builds the model instead of the algorithm's SB3 class (same
            arguments), e.g. a variant with extra losses for a baseline.
        prefill: Trajectories added to the run's task before learning, as
            (actions, score) pairs through ``add_trajectory`` (SPEC §6's rules).
        label: Recorded as the run's ``"hooks"`` entry.
    """

    model_class: Any = None
    prefill: tuple[tuple[tuple[int, ...], float], ...] = ()
    label: str = ""


def import_env_modules(modules: tuple[str, ...] | list[str]) -> None:
    """Import the modules that register the trial's env (``--env-module``)."""
    for name in modules:
        importlib.import_module(name)


def action_space_config(space: gym.Space[Any]) -> dict[str, int]:
    """The task's action space keywords (``num_actions`` or ``action_dim``) for ``space``.

    Raises:
        ValueError: A space a task cannot take (SPEC §1.1: integers ``0..n-1`` or one
            vector of floats).
    """
    from gymnasium import spaces

    if isinstance(space, spaces.Discrete):
        if int(space.start) != 0:
            raise ValueError(
                f"action space {space}: a task's discrete actions are 0..n-1; this one starts "
                f"at {space.start}"
            )
        return {"num_actions": int(space.n)}
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        return {"action_dim": int(space.shape[0])}
    raise ValueError(
        f"action space {space}: a task takes Discrete(n) or a one-dimensional Box; "
        "shaping cannot record these actions"
    )


def versions() -> dict[str, str]:
    """The versions of what shapes a run's numbers."""
    import stable_baselines3
    import torch

    import tamrm

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "gymnasium": gym.__version__,
        "tamrm": tamrm.__version__,
    }


def _algo_class(algo: str) -> Any:
    from stable_baselines3 import A2C, DQN, PPO

    return {"a2c": A2C, "ppo": PPO, "dqn": DQN}[algo]


class _ReturnAsScore(gym.Wrapper[Any, Any, Any, Any]):
    """Puts the ``Monitor``'s episode return (below) in ``info`` as the episode's score."""

    def step(self, action: Any) -> Any:
        obs, reward, terminated, truncated, info = self.env.step(action)
        episode = info.get("episode")
        if episode is not None:
            info[_SCORE_KEY] = float(episode["r"])
        return obs, reward, terminated, truncated, info


def make_venv(settings: TrialSettings, hyper: Hyperparams, seed: int, scored: bool) -> Any:
    """The run's vector env below any shaping: ``Monitor`` first, then the wrappers."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack, VecNormalize

    wrappers = list(hyper.env_wrappers)

    def wrap(env: gym.Env[Any, Any]) -> gym.Env[Any, Any]:
        for cls, kwargs in wrappers:
            env = cls(env, **kwargs)
        return _ReturnAsScore(env) if scored else env

    venv = make_vec_env(
        settings.env,
        n_envs=hyper.n_envs,
        seed=seed,
        env_kwargs=dict(settings.env_kwargs) or None,
        wrapper_class=wrap if (wrappers or scored) else None,
        vec_env_cls=DummyVecEnv,
    )
    if hyper.normalize is not None:
        venv = VecNormalize(venv, **hyper.normalize)
    if hyper.frame_stack:
        venv = VecFrameStack(venv, hyper.frame_stack)
    return venv


def _policy_digest(model: Any) -> str:
    """SHA-256 of the model's final parameters and buffers, in state-dict order."""
    digest = hashlib.sha256()
    for name, tensor in model.policy.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def _recorder(progress: Callable[[int], None], shaped: bool) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class Recorder(BaseCallback):
        """Records each finished episode from its ``Monitor`` info; reports progress."""

        def __init__(self) -> None:
            super().__init__()
            self.columns: dict[str, list[Any]] = {
                "return": [],
                "length": [],
                "timestep": [],
                # The env's own success flag (info["is_success"]), None where it has none.
                "success": [],
            }
            if shaped:
                self.columns.update({"shaped_return": [], "knn_term": [], "potential_term": []})
            self._reported = 0

        def _on_step(self) -> bool:
            dones = self.locals["dones"]
            if dones.any():
                infos = self.locals["infos"]
                cols = self.columns
                for i in np.flatnonzero(dones):
                    episode = infos[i].get("episode")
                    if episode is None:
                        continue
                    cols["return"].append(float(episode["r"]))
                    cols["length"].append(int(episode["l"]))
                    cols["timestep"].append(int(self.num_timesteps))
                    success = infos[i].get("is_success")
                    cols["success"].append(None if success is None else bool(success))
                    if shaped:
                        parts = infos[i].get("shaped_episode", {})
                        cols["shaped_return"].append(float(parts.get("r", np.nan)))
                        cols["knn_term"].append(float(parts.get("knn", np.nan)))
                        cols["potential_term"].append(float(parts.get("potential", np.nan)))
            if self.num_timesteps - self._reported >= _PROGRESS_EVERY:
                progress(self.num_timesteps - self._reported)
                self._reported = self.num_timesteps
            return True

    return Recorder()


def build_model(
    settings: TrialSettings, arm: str, seed: int, backend: Any, hooks: RunHooks | None = None
) -> tuple[Any, Any, Any, Callable[[], None]]:
    """Build the run's model on its env.

    Returns (model, shaped env or None, task id or None, close). ``backend`` (an engine or
    a client) shapes every arm but ``plain``.
    """
    hooks = hooks or RunHooks()
    from tamrm.sb3 import ShapedVecEnv

    hyper = resolve(settings.hyperparams)
    config = arm_task_config(arm, settings.task)
    scored = config is not None and hyper.normalize is not None
    venv = make_venv(settings, hyper, seed, scored)
    shaped = None
    tid = None
    env = venv
    if config is not None:
        tid = task_id(settings, arm, seed)
        with contextlib.suppress(TaskNotFound):
            backend.delete_task(tid)  # left over from an interrupted attempt
        backend.create_task(tid, **action_space_config(venv.action_space), **config)
        for actions, score in hooks.prefill:
            backend.add_trajectory(tid, list(actions), score)
        session = backend.session(tid, venv.num_envs, local=settings.server is not None)
        env = shaped = ShapedVecEnv(venv, session, score_key=_SCORE_KEY if scored else None)
    # SB3 makes a new (empty) log dir at every learn() unless $SB3_LOGDIR names one.
    os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "tamrm-sb3-logs"))
    model = (hooks.model_class or _algo_class(settings.algo))(
        hyper.policy, env, seed=seed, device="cpu", verbose=0, **hyper.algo_kwargs
    )
    if shaped is not None:
        shaped.bind_model(model)
    return model, shaped, tid, env.close


def run_one(
    settings: TrialSettings,
    arm: str,
    seed: int,
    progress: Callable[[int], None] | None = None,
    hooks: RunHooks | None = None,
) -> dict[str, Any]:
    """Train one run and return its record (``DIR/runs/<arm>-<seed>.json``'s content)."""
    import torch

    import tamrm

    torch.set_num_threads(1)
    import_env_modules(settings.env_modules)
    progress = progress or (lambda _n: None)
    started = time.time()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    backend: Any = None
    if arm != "plain":
        backend = tamrm.Engine() if settings.server is None else tamrm.Client(settings.server)
    try:
        model, shaped, tid, close = build_model(settings, arm, seed, backend, hooks)
        recorder = _recorder(progress, shaped is not None)
        try:
            model.learn(total_timesteps=settings.timesteps, callback=recorder)
            shaping: dict[str, Any] | None = None
            if shaped is not None:
                stats = shaped.take_stats()
                task = backend.get_task(tid)
                steps = max(1, stats.env_steps)
                shaping = {
                    "task": asdict(task.config),
                    "knn_term_sum": stats.knn_term,
                    "potential_term_sum": stats.potential_term,
                    "knn_active_frac": stats.knn_active / steps,
                    "pool_size": task.stats.pool_size,
                    "pool_version": task.stats.pool_version,
                    "best_score": task.stats.best_score,
                    "worst_score": task.stats.worst_score,
                    "episodes_completed": task.stats.episodes_completed,
                }
        finally:
            close()
        if tid is not None and settings.server is not None:
            backend.delete_task(tid)
    finally:
        if backend is not None:
            backend.close()
    progress(model.num_timesteps - recorder._reported)
    return {
        "format": RECORD_FORMAT,
        "arm": arm,
        "seed": seed,
        "config": settings.run_config(arm),
        "backend": None if arm == "plain" else ("engine" if settings.server is None else "server"),
        "timesteps": int(model.num_timesteps),
        "episodes": recorder.columns,
        "shaping": shaping,
        "policy_sha256": _policy_digest(model),
        "wall_time_s": round(time.perf_counter() - t0, 3),
        # This process's CPU time: the run's cost whatever else the machine was doing.
        "cpu_time_s": round(time.process_time() - cpu0, 3),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
        "versions": versions(),
        **({"hooks": hooks.label} if hooks is not None and hooks.label else {}),
    }
