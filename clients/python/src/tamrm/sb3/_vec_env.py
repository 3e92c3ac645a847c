"""The Stable-Baselines3 ``VecEnv`` wrapper whose rewards are shaped (:class:`ShapedVecEnv`).

Each vector step is one call of the native fast path (``VecStep``), or, for the steps it
declines, a session step built here: SB3's ``dones`` split into terminated and truncated,
V(s) and V(s') of the bound value function (evaluated once per observation), the episode
scores. :class:`ShapingStats` sums what was shaped, for :class:`tamrm.sb3.ShapingLogger`.
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from types import FrameType
from typing import Any

import numpy as np
import numpy.typing as npt
from stable_baselines3.common.vec_env import (
    VecCheckNan,
    VecEnv,
    VecEnvWrapper,
    VecMonitor,
    VecNormalize,
    VecVideoRecorder,
)
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs

from tamrm import _bridge
from tamrm._session import Session
from tamrm._values import ObsBatch, ValueFn, copy_obs, set_obs_row, value_kwargs
from tamrm._wrapping import check_session, close_session
from tamrm.sb3._critic import ModelValueFn, model_value_fn

__all__ = ["ShapedVecEnv", "ShapingStats", "shaped_env_of"]


_MONITOR_ABOVE = (
    "VecMonitor above ShapedVecEnv would record the shaped rewards as the episode returns "
    "(SB3's ep_rew_mean); put the monitor below it: ShapedVecEnv(VecMonitor(venv), session) "
    "(make_vec_env already puts a Monitor in every env, so no VecMonitor is needed there)"
)


def _refuse_monitor_above() -> None:
    """Raise if the ``env_is_wrapped`` call in progress comes from a ``VecMonitor`` being built.

    ``VecMonitor.__init__`` asks the env below it whether it is wrapped in a ``Monitor``;
    through any wrappers in between, the question reaches the :class:`ShapedVecEnv`.
    """
    frame: FrameType | None = sys._getframe(2)  # the caller of ShapedVecEnv.env_is_wrapped
    while frame is not None and frame.f_code.co_name == "env_is_wrapped":
        frame = frame.f_back
    if (
        frame is not None
        and frame.f_code.co_name == "__init__"
        and isinstance(frame.f_locals.get("self"), VecMonitor)
    ):
        raise ValueError(_MONITOR_ABOVE)


def _keeps_observations(wrapper: VecEnv) -> bool:
    """Whether an SB3 wrapper passes the observations through unchanged."""
    if isinstance(wrapper, VecNormalize):
        return not wrapper.norm_obs
    return isinstance(wrapper, (VecMonitor, VecCheckNan, VecVideoRecorder))


def _obs_batch(obs: VecEnvObs) -> ObsBatch:
    """The observations for the value helpers: arrays or dicts of arrays (a tuple: one array)."""
    return np.asarray(obs) if isinstance(obs, tuple) else obs


def _evaluate(value_fn: ValueFn, obs: ObsBatch, size: int) -> npt.NDArray[np.float64]:
    """``value_fn`` on one batch: V(s) ``(size,)`` or Q(s, ·) ``(size, num_actions)``."""
    out = np.asarray(value_fn(obs), dtype=np.float64)
    if out.shape == (size, 1):
        out = out[:, 0]
    if out.shape == (size,) or (out.ndim == 2 and out.shape[0] == size):
        return out
    raise ValueError(
        f"value_fn returned shape {out.shape} for {size} observations; expected ({size},) "
        f"state values or ({size}, num_actions) Q-values"
    )


def _with_rows(obs: ObsBatch, infos: list[dict[str, Any]], rows: list[int]) -> ObsBatch:
    """A copy of ``obs`` with the given rows replaced by their ``terminal_observation``."""
    out = copy_obs(obs)
    for row in rows:
        set_obs_row(out, row, infos[row]["terminal_observation"])
    return out


def _end_flags(
    dones: npt.NDArray[np.bool_], done_rows: list[int], infos: list[dict[str, Any]]
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """SB3's ``dones`` split into (terminated, truncated) by ``TimeLimit.truncated``."""
    truncated = np.zeros(len(dones), dtype=np.bool_)
    for row in done_rows:
        truncated[row] = bool(infos[row].get("TimeLimit.truncated", False))
    return dones & ~truncated, truncated


# Rows of ShapedVecEnv._acc: the sums of R_meta, r(t), F, knn_active (0/1) and R.
_SUMS = 5


@dataclass(frozen=True)
class ShapingStats:
    """Sums over the environment steps a :class:`ShapedVecEnv` shaped (see ``take_stats``).

    Attributes:
        env_steps: Environment steps shaped (vector steps times ``num_envs``).
        reward_env: Sum of the environment rewards R.
        knn_term: Sum of alpha * r(t).
        potential_term: Sum of beta * F.
        knn_active: Steps on which the kNN term was active.
        pool_version: The task's pool version after the last of them (-1: no step yet).
    """

    env_steps: int = 0
    reward_env: float = 0.0
    knn_term: float = 0.0
    potential_term: float = 0.0
    knn_active: int = 0
    pool_version: int = -1

    def __add__(self, later: ShapingStats) -> ShapingStats:
        """The sums over both spans (``later``'s pool version if it has one)."""
        return ShapingStats(
            self.env_steps + later.env_steps,
            self.reward_env + later.reward_env,
            self.knn_term + later.knn_term,
            self.potential_term + later.potential_term,
            self.knn_active + later.knn_active,
            later.pool_version if later.env_steps else self.pool_version,
        )


class ShapedVecEnv(VecEnvWrapper):
    """A Stable-Baselines3 ``VecEnv`` wrapper whose rewards are shaped by tamrm.

    Every ``step`` of the vector env is one round trip on ``session``. Make it the
    outermost wrapper (the model's ``env``) when binding the model's value estimates, so
    that the observations it passes to the model are the ones the model sees.

    Args:
        venv: The SB3 vector environment (``num_envs`` must equal ``session.num_envs``).
        session: An open session with ``venv.num_envs`` environments.
        value_fn: Optional ``value_fn(obs_batch)`` returning V(s) ``(B,)`` or Q(s, ·)
            ``(B, num_actions)``; see also :meth:`bind_model`. Without one, F = 0.
        score_key: Optional ``info`` key holding the episode score S (SPEC §6) on the step
            that ends an episode, e.g. ``100 / steps`` in a sparse maze. Ending rows whose
            ``info`` lacks the key (e.g. a ``TimeLimit`` truncation) get the server's
            default, the sum of the episode's environment rewards.
        close_session: Whether :meth:`close` closes ``session``. By default (``None``) it
            does, unless the session is open in a ``with`` block (which then owns it).
    """

    def __init__(
        self,
        venv: VecEnv,
        session: Session,
        value_fn: ValueFn | None = None,
        *,
        score_key: str | None = None,
        close_session: bool | None = None,
    ) -> None:
        super().__init__(venv)
        self.session = session  # checked, with the fast path bound to it (the setter)
        self.close_session = close_session
        self.value_fn = value_fn
        self.score_key = score_key
        self._obs: ObsBatch | None = None
        # The value function's output on self._obs: (value_fn, its version, values).
        self._values: tuple[ValueFn, Any, npt.NDArray[np.float64]] | None = None
        self._actions: npt.NDArray[Any] | None = None
        config = session.config
        n = venv.num_envs
        self._action_shape = (n,) if config.discrete else (n, config.action_dim)
        # Per env (columns), the sums over its current episode (rows, see _SUMS): the
        # shaped return, r(t), F, the steps with kNN active and R. alpha and beta multiply
        # the sums of r(t) and F when they are read.
        self._acc = np.zeros((_SUMS, n), dtype=np.float64)
        # For take_stats: the sums of the episodes ended since the last call, and the
        # columns of self._acc as they were at the last call.
        self._ended = np.zeros(_SUMS, dtype=np.float64)
        self._taken = np.zeros((_SUMS, n), dtype=np.float64)
        self._env_steps = 0  # shaped since the last take_stats
        # Tests turn the fast path off to compare with the general path.
        self._fast_path = True

    @property
    def session(self) -> Session:
        """The session that shapes every step.

        It can be replaced by another open session of ``num_envs`` environments; the
        next step is then the new session's (its check raises ``ValueError`` as the
        constructor's does).
        """
        return self._session

    @session.setter
    def session(self, session: Session) -> None:
        check_session(session, self.venv.num_envs, self.venv.action_space, "the VecEnv")
        config = session.config
        # The fast path: the whole step in one native call on this session
        # (tamrm._native.VecStep, which declines the steps it does not handle).
        self._vec_step = _bridge.VecStep(
            session._native,
            ModelValueFn,
            0 if config.discrete else config.action_dim,
            config.alpha,
            config.beta,
        )
        self._session = session

    def env_is_wrapped(self, wrapper_class: type[Any], indices: Any = None) -> list[bool]:
        """Whether the sub-environments are wrapped in ``wrapper_class`` (SB3's query).

        Raises:
            ValueError: The query comes from a ``VecMonitor`` being put above this wrapper
                (its episode returns would be the shaped ones).
        """
        _refuse_monitor_above()
        wrapped: list[bool] = self.venv.env_is_wrapped(wrapper_class, indices)
        return wrapped

    def bind_model(self, model: Any, *, fast: bool = True) -> ShapedVecEnv:
        """Use ``model``'s own value estimates for the potential term F.

        See :func:`model_value_fn` (``fast``: a plain MLP critic evaluated natively).
        Call it after the model is built (the model needs the env to be built).
        Returns ``self``.
        """
        get_env = getattr(model, "get_env", None)
        env = get_env() if callable(get_env) else None
        changing: list[str] = []
        while isinstance(env, VecEnvWrapper) and env is not self:
            if isinstance(env, VecMonitor):
                raise ValueError(_MONITOR_ABOVE)
            if not _keeps_observations(env):
                changing.append(type(env).__name__)
            env = env.venv
        if env is not None and env is not self:
            warnings.warn(
                "the model's env does not contain this ShapedVecEnv: the values are computed "
                "on this wrapper's observations, not necessarily the model's",
                stacklevel=2,
            )
        elif changing:
            warnings.warn(
                f"the model's env wraps this ShapedVecEnv in {', '.join(changing)}, which "
                "change the observations: the values are computed on this wrapper's "
                "(unchanged) observations; make ShapedVecEnv the outermost wrapper",
                stacklevel=2,
            )
        self.value_fn = model_value_fn(model, fast=fast)
        return self

    def take_stats(self) -> ShapingStats:
        """Return the sums over the steps shaped since the last call, and start new ones."""
        # The episodes that ended since the last call, plus what the episodes in progress
        # added since then (their sums at the last call are in self._taken).
        sums = self._ended + (self._acc - self._taken).sum(axis=1)
        self._ended = np.zeros(_SUMS, dtype=np.float64)
        self._taken = self._acc.copy()
        env_steps, self._env_steps = self._env_steps, 0
        _, knn, potential, knn_active, reward_env = sums.tolist()
        if not env_steps:
            return ShapingStats()
        cfg = self.session.config
        return ShapingStats(
            int(env_steps),
            reward_env,
            cfg.alpha * knn,
            cfg.beta * potential,
            int(knn_active),
            self.session.pool_version,
        )

    def _step_values(
        self,
        obs: ObsBatch,
        infos: list[dict[str, Any]],
        done_rows: list[int],
        truncated: npt.NDArray[np.bool_] | None,
    ) -> dict[str, npt.NDArray[np.float64]]:
        """The step's ``values``/``next_values`` (or Q-value) keywords for the session.

        A value function with a ``version()`` method (:class:`ModelValueFn`) is evaluated
        once per observation: V(s') of the observations returned now are the next step's
        V(s), kept while ``version()`` stays the same. Each call is one batch of
        ``num_envs`` observations (a network's output for a row may depend on the batch
        size, not on the other rows), so the values are bit for bit those of evaluating
        V(s) and V(s') separately on every step. On a step where an environment was
        truncated, V(s') of its real last observation takes one more batch; a terminated
        one needs none (the server takes V(s') = 0).
        """
        value_fn = self.value_fn
        if value_fn is None:
            return {}
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        finals = [row for row in done_rows if infos[row].get("terminal_observation") is not None]
        version_of = getattr(value_fn, "version", None)
        if not callable(version_of):
            # A plain function may change between any two calls: both batches, every step.
            next_obs = _with_rows(obs, infos, finals) if finals else obs
            return value_kwargs(value_fn, self._obs, next_obs, self.num_envs)
        version = version_of()
        cached = self._values
        if cached is not None and cached[0] is value_fn and cached[1] == version:
            current = cached[2]
        else:
            current = _evaluate(value_fn, self._obs, self.num_envs)
        following = _evaluate(value_fn, obs, self.num_envs)
        self._values = (value_fn, version, following)
        rows = [row for row in finals if truncated is not None and truncated[row]]
        if rows:
            following = following.copy()
            following[rows] = _evaluate(value_fn, _with_rows(obs, infos, rows), self.num_envs)[rows]
        if current.ndim == 1:
            return {"values": current, "next_values": following}
        return {"q_values": current, "next_q_values": following}

    def close(self) -> None:
        """Close the VecEnv, then the session if the wrapper owns it (``close_session``)."""
        try:
            self.venv.close()
        finally:
            close_session(self.session, self.close_session)

    def reset(self) -> VecEnvObs:
        """Reset every sub-environment; abandon the episodes that were in progress."""
        obs = self.venv.reset()
        # The abandoned episodes' steps stay in the stats, not in any episode's sums.
        self._ended += (self._acc - self._taken).sum(axis=1)
        self._acc[:] = 0.0
        self._taken[:] = 0.0
        self._values = None
        in_progress = self.session.episodes_in_progress
        if in_progress.any():
            self.session.abandon(np.flatnonzero(in_progress))
        self._obs = _obs_batch(obs)
        return obs

    def step_async(self, actions: npt.NDArray[Any]) -> None:
        """Send the actions to the wrapped env (and remember them for shaping)."""
        self._actions = actions
        self.venv.step_async(actions)

    def step_wait(
        self,
    ) -> tuple[VecEnvObs, npt.NDArray[np.float32], npt.NDArray[np.bool_], list[dict[str, Any]]]:
        """Wait for the step, shape its rewards in one round trip and return them."""
        raw_obs, rewards, dones, infos = self.venv.step_wait()
        if self._fast_path:
            session = self.session
            try:
                shaped = self._vec_step.step(self, self._actions, raw_obs, rewards, dones, infos)
            except _bridge.StatusError as exc:
                raise session._failed(exc) from None
            except KeyboardInterrupt:
                session._interrupted()
                raise
            if shaped is not None:
                return raw_obs, shaped, dones, infos
        dones = np.asarray(dones, dtype=np.bool_)
        any_done = bool(dones.any())
        obs = _obs_batch(raw_obs)
        done_rows: list[int] = np.flatnonzero(dones).tolist() if any_done else []
        # None: no env ended (all false), one array fewer to check and send.
        terminated = truncated = None
        if done_rows:
            terminated, truncated = _end_flags(dones, done_rows, infos)

        values = self._step_values(obs, infos, done_rows, truncated)

        scores = None
        if self.score_key is not None and done_rows:
            scores = {
                row: float(infos[row][self.score_key])
                for row in done_rows
                if self.score_key in infos[row]
            }

        actions = np.asarray(self._actions)
        if actions.shape != self._action_shape:
            actions = actions.reshape(self._action_shape)
        rewards = np.asarray(rewards, dtype=np.float64)
        result = self.session.step(
            actions, rewards, terminated, truncated, episode_scores=scores or None, **values
        )
        # The episode sums, `_env_steps`, the info keys and `shaped_episode`: the same
        # native code as the fast path's.
        cfg = self.session.config
        _bridge.record_step(self, infos, dones, rewards, result, cfg.alpha, cfg.beta)
        self._obs = obs
        return raw_obs, result.rewards.astype(np.float32), dones, infos


def shaped_env_of(training_env: VecEnv, callback: str) -> ShapedVecEnv:
    """The :class:`ShapedVecEnv` in a model's env, found through its ``venv`` chain.

    Raises:
        ValueError: There is none; the message tells to pass it to ``callback``.
    """
    env: Any = training_env
    while isinstance(env, VecEnvWrapper):
        if isinstance(env, ShapedVecEnv):
            return env
        env = env.venv
    raise ValueError(
        f"{callback}: the model's env contains no ShapedVecEnv; pass it: {callback}(env=...)"
    )
