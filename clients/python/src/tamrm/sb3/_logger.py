"""The shaped reward's parts in a Stable-Baselines3 model's logger (:class:`ShapingLogger`)."""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback

from tamrm.sb3._vec_env import ShapedVecEnv, ShapingStats, shaped_env_of

__all__ = ["ShapingLogger"]


class ShapingLogger(BaseCallback):
    """Record the shaped reward's parts in the model's logger (TensorBoard, CSV, stdout).

    ``model.learn(total, callback=tamrm.sb3.ShapingLogger())``: at the end of every
    rollout it records, as means per environment step over all steps since the logger
    last wrote a row, ``tamrm/reward_env`` (R), ``tamrm/knn_term`` (alpha * r(t)),
    ``tamrm/potential_term`` (beta * F) and ``tamrm/knn_active_frac``, and the task's
    ``tamrm/pool_size`` (asked from the server with ``get_task`` only when the pool
    version changed since the last time).

    Args:
        env: The :class:`ShapedVecEnv`; by default the one in the model's env (found
            through its ``venv`` chain).
        prefix: The keys' prefix.
    """

    def __init__(self, env: ShapedVecEnv | None = None, *, prefix: str = "tamrm/") -> None:
        super().__init__()
        self.env = env
        self.prefix = prefix
        self._totals = ShapingStats()
        self._pool = (-1, 0)  # (pool version, pool size) of the last get_task

    def _init_callback(self) -> None:
        if self.env is None:
            self.env = shaped_env_of(self.training_env, "ShapingLogger")
        self.env.take_stats()  # steps shaped before learn() are not this run's
        self._totals = ShapingStats()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        assert self.env is not None
        key = self.prefix + "reward_env"
        if key not in self.logger.name_to_value:  # the logger wrote a row (or none yet)
            self._totals = ShapingStats()
        totals = self._totals = self._totals + self.env.take_stats()
        if totals.env_steps == 0:
            return
        steps = totals.env_steps
        self.logger.record(key, totals.reward_env / steps)
        self.logger.record(self.prefix + "knn_term", totals.knn_term / steps)
        self.logger.record(self.prefix + "potential_term", totals.potential_term / steps)
        self.logger.record(self.prefix + "knn_active_frac", totals.knn_active / steps)
        if totals.pool_version != self._pool[0]:
            session = self.env.session
            stats = session._client.get_task(session.task_id).stats
            self._pool = (totals.pool_version, stats.pool_size)
        self.logger.record(self.prefix + "pool_size", self._pool[1])
