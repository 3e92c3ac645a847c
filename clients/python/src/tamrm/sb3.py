"""Stable-Baselines3 integration (install with ``pip install 'tamrm[sb3]'``).

:class:`ShapedVecEnv` wraps an SB3 ``VecEnv`` so that the rewards the model learns from
are the shaped ones; no change to SB3 is needed::

    venv = make_vec_env("CartPole-v1", n_envs=8)
    with client.session("cartpole", venv.num_envs) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env)
        env.bind_model(model)  # optional: F from the model's own value estimates
        model.learn(100_000)

SB3 resets a sub-environment inside the step that ended its episode: the returned
observation is already the reset one and the real last observation is in
``infos[i]["terminal_observation"]``; ``infos[i]["TimeLimit.truncated"]`` tells a time
limit from a real termination. Both are used here: a truncated step is sent as
``truncated`` with V(s') of the real last observation, a terminated one as
``terminated`` (the server takes V(s') = 0).

Each env's ``info`` gets ``original_reward``, ``knn_reward``, ``potential``,
``shaping_step``, ``knn_active`` and ``pool_version``. Episode statistics recorded by
SB3's ``Monitor`` (below the ``VecEnv``, as ``make_vec_env`` puts it) or by a
``VecMonitor`` below this wrapper stay in terms of the original reward (``info["episode"]``,
SB3's ``ep_rew_mean``); the shaped return and its parts are beside them, in
``info["shaped_episode"]`` (``r``: the sum of R_meta, ``knn``: of alpha * r(t),
``potential``: of beta * F, ``l``: the length). A ``VecMonitor`` above this wrapper is
refused (it would record the shaped returns).
"""

from __future__ import annotations

import sys
import warnings
from types import FrameType
from typing import Any

import numpy as np
import numpy.typing as npt

try:
    from stable_baselines3.common.vec_env import (
        VecCheckNan,
        VecEnv,
        VecEnvWrapper,
        VecMonitor,
        VecNormalize,
        VecVideoRecorder,
    )
    from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs
except ModuleNotFoundError as _missing:  # pragma: no branch - depends on the install
    if (_missing.name or "").split(".")[0] not in ("stable_baselines3", "torch"):
        raise
    raise ImportError(
        f"tamrm.sb3 needs Stable-Baselines3 ({_missing.name} is not installed): "
        "pip install 'tamrm[sb3]' (it brings PyTorch; see docs/python.md for CPU-only "
        "wheels)",
        name=_missing.name,
    ) from None

from tamrm._session import Session
from tamrm._values import ObsBatch, ValueFn, copy_obs, set_obs_row, value_kwargs
from tamrm._wrapping import check_session, close_session

__all__ = ["ShapedVecEnv", "model_value_fn"]


def model_value_fn(model: Any) -> ValueFn:
    """Return a ``value_fn`` computing a Stable-Baselines3 model's own value estimates.

    - Models with a Q-network (``DQN``: ``model.policy.q_net``) give Q(s, ·); the server
      takes V(s) = max_a Q(s, a).
    - Actor-critic models (``A2C``, ``PPO``: ``model.policy.predict_values``) give V(s).

    Observations are preprocessed exactly as the policy does (``obs_to_tensor``), and
    the evaluation runs under ``torch.no_grad()``.

    Raises:
        TypeError: The model's policy has neither ``q_net`` nor ``predict_values``.
    """
    import torch

    policy = model.policy
    if hasattr(policy, "q_net"):
        q_net = policy.q_net

        def q_values(obs: ObsBatch) -> npt.NDArray[np.float64]:
            tensor, _ = policy.obs_to_tensor(obs)
            with torch.no_grad():
                out = q_net(tensor)
            return np.asarray(out.cpu().numpy(), dtype=np.float64)

        return q_values
    if hasattr(policy, "predict_values"):

        def state_values(obs: ObsBatch) -> npt.NDArray[np.float64]:
            tensor, _ = policy.obs_to_tensor(obs)
            with torch.no_grad():
                out = policy.predict_values(tensor)
            return np.asarray(out.cpu().numpy(), dtype=np.float64).reshape(-1)

        return state_values
    raise TypeError(
        f"{type(model).__name__}: its policy has neither q_net (DQN) nor predict_values "
        "(A2C/PPO); pass your own value_fn"
    )


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
        check_session(session, venv.num_envs, venv.action_space, "the VecEnv")
        self.session = session
        self.close_session = close_session
        self.value_fn = value_fn
        self.score_key = score_key
        self._obs: ObsBatch | None = None
        self._actions: npt.NDArray[Any] | None = None
        # Per env, the current episode's shaped return and its parts (info["shaped_episode"]).
        self._episode = np.zeros((venv.num_envs, 4), dtype=np.float64)

    def env_is_wrapped(self, wrapper_class: type[Any], indices: Any = None) -> list[bool]:
        """Whether the sub-environments are wrapped in ``wrapper_class`` (SB3's query).

        Raises:
            ValueError: The query comes from a ``VecMonitor`` being put above this wrapper
                (its episode returns would be the shaped ones).
        """
        _refuse_monitor_above()
        wrapped: list[bool] = self.venv.env_is_wrapped(wrapper_class, indices)
        return wrapped

    def bind_model(self, model: Any) -> ShapedVecEnv:
        """Use ``model``'s own value estimates for the potential term F.

        See :func:`model_value_fn`. Call it after the model is built (the model needs the
        env to be built).
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
        self.value_fn = model_value_fn(model)
        return self

    def close(self) -> None:
        """Close the VecEnv, then the session if the wrapper owns it (``close_session``)."""
        try:
            self.venv.close()
        finally:
            close_session(self.session, self.close_session)

    def reset(self) -> VecEnvObs:
        """Reset every sub-environment; abandon the episodes that were in progress."""
        obs = self.venv.reset()
        self._episode[:] = 0.0
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
        obs = _obs_batch(raw_obs)
        dones = np.asarray(dones, dtype=np.bool_)
        done_rows = np.flatnonzero(dones)
        truncated = np.zeros(self.num_envs, dtype=np.bool_)
        for row in done_rows.tolist():
            truncated[row] = bool(infos[row].get("TimeLimit.truncated", False))
        terminated = dones & ~truncated

        values: dict[str, npt.NDArray[np.float64]] = {}
        if self.value_fn is not None:
            if self._obs is None:
                raise RuntimeError("call reset() before step()")
            next_obs = obs
            if done_rows.size:
                next_obs = copy_obs(obs)
                for row in done_rows.tolist():
                    final = infos[row].get("terminal_observation")
                    if final is not None:
                        set_obs_row(next_obs, row, final)
            values = value_kwargs(self.value_fn, self._obs, next_obs, self.num_envs)

        scores = None
        if self.score_key is not None:
            scores = {
                row: float(infos[row][self.score_key])
                for row in done_rows.tolist()
                if self.score_key in infos[row]
            }

        actions = np.asarray(self._actions)
        if self.session.config.discrete:
            actions = actions.reshape(self.num_envs)
        else:
            actions = actions.reshape(self.num_envs, self.session.config.action_dim)
        result = self.session.step(
            actions,
            np.asarray(rewards, dtype=np.float64),
            terminated,
            truncated,
            episode_scores=scores or None,
            **values,
        )
        cfg = self.session.config
        self._episode += np.stack(
            [
                result.rewards,
                cfg.alpha * result.knn_rewards,
                cfg.beta * result.potentials,
                np.ones(self.num_envs),
            ],
            axis=1,
        )
        for i, info in enumerate(infos):
            if dones[i]:
                shaped_r, knn_part, potential_part, length = self._episode[i].tolist()
                info["shaped_episode"] = {
                    "r": shaped_r,
                    "knn": knn_part,
                    "potential": potential_part,
                    "l": int(length),
                }
                self._episode[i] = 0.0
            info["original_reward"] = float(rewards[i])
            info["knn_reward"] = float(result.knn_rewards[i])
            info["potential"] = float(result.potentials[i])
            info["shaping_step"] = int(result.steps[i])
            info["knn_active"] = bool(result.knn_active[i])
            info["pool_version"] = result.pool_version
        self._obs = obs
        return raw_obs, result.rewards.astype(np.float32), dones, infos
