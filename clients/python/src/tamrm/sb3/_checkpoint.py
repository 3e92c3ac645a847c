"""Stable-Baselines3 checkpoints that carry the task's pool.

:class:`PoolCheckpointCallback` saves it beside each model checkpoint, :func:`restore_pool`
puts it back. The pool file is the pool export format (docs/storage.md, "Pool export format"), named
after the model's file: ``<name_prefix>_<steps>_steps.pool.jsonl`` beside SB3's
``<name_prefix>_<steps>_steps.zip`` (:func:`pool_path`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import CheckpointCallback

from tamrm._calls import CLIENT_TIMEOUT, Timeout
from tamrm._types import Task
from tamrm.sb3._vec_env import ShapedVecEnv, shaped_env_of

__all__ = ["POOL_SUFFIX", "PoolCheckpointCallback", "pool_path", "restore_pool"]

#: What follows a model checkpoint's name (without ``.zip``) in its pool file's name.
POOL_SUFFIX = ".pool.jsonl"


def pool_path(model_path: str | os.PathLike[str]) -> Path:
    """The pool file of a model checkpoint: its path without ``.zip``, plus ``.pool.jsonl``.

    ``ckpt/a2c_5000_steps.zip`` (or ``ckpt/a2c_5000_steps``, as SB3's ``load`` takes it)
    -> ``ckpt/a2c_5000_steps.pool.jsonl``.
    """
    path = Path(model_path)
    if path.suffix == ".zip":
        path = path.with_suffix("")
    return path.with_name(path.name + POOL_SUFFIX)


class PoolCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` that also saves the task's pool beside each model.

    Every ``save_freq`` calls, before SB3 saves ``<name_prefix>_<steps>_steps.zip`` in
    ``save_path``, the pool of the :class:`ShapedVecEnv`'s task is exported to
    ``<name_prefix>_<steps>_steps.pool.jsonl`` beside it (:func:`pool_path`; written whole
    or not at all), through the session's own client or engine: the pool as it is after
    the step that triggered the checkpoint, the one the saved model was trained against.
    :func:`restore_pool` puts it back, so that training resumed from the checkpoint shapes
    as if it had never stopped. (Episodes in progress at the checkpoint are not saved: a
    resumed run starts new ones, as SB3 resets its envs.)

    Args:
        save_freq, save_path, name_prefix, save_replay_buffer, save_vecnormalize, verbose:
            As SB3's ``CheckpointCallback``.
        env: The :class:`ShapedVecEnv`; by default the one in the model's env (found
            through its ``venv`` chain, as :class:`ShapingLogger` finds it).
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str,
        name_prefix: str = "rl_model",
        save_replay_buffer: bool = False,
        save_vecnormalize: bool = False,
        verbose: int = 0,
        *,
        env: ShapedVecEnv | None = None,
    ) -> None:
        super().__init__(
            save_freq,
            save_path,
            name_prefix=name_prefix,
            save_replay_buffer=save_replay_buffer,
            save_vecnormalize=save_vecnormalize,
            verbose=verbose,
        )
        self.env = env

    def _init_callback(self) -> None:
        super()._init_callback()
        if self.env is None:
            self.env = shaped_env_of(self.training_env, "PoolCheckpointCallback")

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            assert self.env is not None
            model = os.path.join(self.save_path, f"{self.name_prefix}_{self.num_timesteps}_steps")
            path = pool_path(model)
            session = self.env.session
            session._client.export_pool(session.task_id, path)
            if self.verbose >= 2:
                print(f"Saving the pool of task {session.task_id!r} to {path}")
        return bool(super()._on_step())


def restore_pool(
    client: Any,
    model_path: str | os.PathLike[str],
    task_id: str | None = None,
    *,
    replace: bool = True,
    timeout: Timeout = CLIENT_TIMEOUT,
) -> Task:
    """Restore the pool saved beside a model checkpoint (:class:`PoolCheckpointCallback`).

    ``client.import_pool(pool_path(model_path), task_id, replace=replace)``: the pool goes
    into ``task_id`` (default: the task it was saved from), created with the saved config
    if missing. ``replace`` is true by default, since restoring a checkpoint means its pool
    and no other: a task of another config is re-created, a non-empty pool is reset.

    Args:
        client: A :class:`tamrm.Client` or :class:`tamrm.Engine`.
        model_path: The model checkpoint, with or without ``.zip``.
        task_id: The task to restore into; ``None``: the one the pool was saved from.
        replace: As :meth:`tamrm.Client.import_pool`.
        timeout: Each call's deadline.

    Returns:
        The task after the import.

    Raises:
        FileNotFoundError: No pool file beside the model.
        PoolFileError: The pool file is malformed (nothing was imported).
    """
    path = pool_path(model_path)
    if not path.exists():
        raise FileNotFoundError(
            f"no pool file beside the model {os.fspath(model_path)!r}: {os.fspath(path)!r} "
            "(tamrm.sb3.PoolCheckpointCallback saves one with each checkpoint)"
        )
    task: Task = client.import_pool(path, task_id, replace=replace, timeout=timeout)
    return task
