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

The bound model's critic is evaluated once per observation (see :class:`ModelValueFn`),
with the same values as evaluating V(s) and V(s') on every step. :class:`ShapingLogger`
records the shaped parts in the model's logger::

    model.learn(100_000, callback=tamrm.sb3.ShapingLogger())
"""

from __future__ import annotations

import itertools
import sys
import warnings
from dataclasses import dataclass
from types import FrameType
from typing import Any

import numpy as np
import numpy.typing as npt

try:
    from stable_baselines3.common.callbacks import BaseCallback
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

from tamrm import _bridge
from tamrm._session import Session
from tamrm._values import ObsBatch, ValueFn, copy_obs, set_obs_row, value_kwargs
from tamrm._wrapping import check_session, close_session

__all__ = ["ModelValueFn", "ShapedVecEnv", "ShapingLogger", "ShapingStats", "model_value_fn"]


class _MlpCritic:
    """An SB3 critic that is a plain MLP, evaluated natively on views of its parameters.

    Built by :meth:`of` for the usual SB3 policies (``MlpPolicy`` of A2C, PPO, DQN): a
    ``Box`` (non-image) observation space, a ``FlattenExtractor``, and a stack of
    ``nn.Linear`` layers with ``Tanh``/``ReLU`` activations, float32 on the CPU. It runs
    in the native extension (``tamrm._native.Mlp``) on numpy views of the torch
    parameters (``Tensor.numpy()`` shares the memory), so every in-place update
    (optimizer steps, ``load_state_dict``) is seen without a copy; a parameter whose
    storage was replaced (``.data = ...``) makes :meth:`current` false and the critic is
    built again. The values equal torch's up to float32 rounding (the same float32
    weights, another summation order, tanh within 8 ulps): about 1e-7 relative.
    """

    def __init__(
        self,
        params: tuple[Any, ...],
        layers: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], str]],
    ) -> None:
        self._params = params
        self._ptrs = [t.data_ptr() for t in params]
        self._mlp = _bridge.Mlp(layers)

    @classmethod
    def of(cls, policy: Any) -> _MlpCritic | None:
        """The native critic of ``policy``, or ``None`` when it is not a plain MLP critic."""
        import torch
        from gymnasium import spaces
        from stable_baselines3.common.preprocessing import is_image_space
        from stable_baselines3.common.torch_layers import FlattenExtractor

        space = getattr(policy, "observation_space", None)
        if not isinstance(space, spaces.Box) or is_image_space(space):
            return None
        if hasattr(policy, "q_net"):
            extractor = getattr(policy.q_net, "features_extractor", None)
            modules = [policy.q_net.q_net]
        else:
            extractor = getattr(policy, "vf_features_extractor", None)
            mlp = getattr(policy, "mlp_extractor", None)
            if mlp is None:
                return None
            modules = [getattr(mlp, "value_net", None), getattr(policy, "value_net", None)]
        if type(extractor) is not FlattenExtractor:
            return None
        flat: list[Any] = []
        for module in modules:
            if type(module) is torch.nn.Sequential:
                flat.extend(module)
            elif module is not None:
                flat.append(module)
            else:
                return None
        layers: list[tuple[Any, Any, str]] = []
        params: list[Any] = []
        for module in flat:
            kind = type(module)
            if kind is torch.nn.Linear and module.bias is not None:
                weight, bias = module.weight, module.bias
                if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in (weight, bias)):
                    return None
                params += [weight, bias]
                layers.append((weight.detach().numpy(), bias.detach().numpy(), ""))
            elif kind in (torch.nn.Tanh, torch.nn.ReLU) and layers and not layers[-1][2]:
                w, b, _ = layers[-1]
                layers[-1] = (w, b, "tanh" if kind is torch.nn.Tanh else "relu")
            elif kind is not torch.nn.Identity:
                return None
        if not layers:
            return None
        return cls(tuple(params), layers)

    def current(self) -> bool:
        """Whether every parameter still has the storage the views were taken of."""
        return [t.data_ptr() for t in self._params] == self._ptrs

    def __call__(self, obs: ObsBatch) -> npt.NDArray[np.float32]:
        """The critic's output for a batch: ``(B, out)``, float32."""
        x = np.asarray(obs, dtype=np.float32)
        return self._mlp(np.ascontiguousarray(x.reshape(x.shape[0], -1)))


class ModelValueFn:
    """A Stable-Baselines3 model's own value estimates as a ``value_fn`` (:func:`model_value_fn`).

    Calling it evaluates the model's current policy (``model.policy``) on a batch of
    observations; :meth:`version` tells :class:`ShapedVecEnv` when values it computed
    earlier may be stale.

    Args:
        model: The SB3 model (its ``policy`` is read at every call).
        fast: Evaluate a plain MLP critic natively on views of its parameters (see
            :func:`model_value_fn`) instead of through torch. Other policies always go
            through torch.
    """

    def __init__(self, model: Any, *, fast: bool = True) -> None:
        import torch

        policy = model.policy
        if not hasattr(policy, "q_net") and not hasattr(policy, "predict_values"):
            raise TypeError(
                f"{type(model).__name__}: its policy has neither q_net (DQN) nor "
                "predict_values (A2C/PPO); pass your own value_fn"
            )
        self.model = model
        self.fast = fast
        self._no_grad = torch.no_grad
        self._tensors: tuple[Any, tuple[Any, ...], tuple[int, ...]] | None
        self._tensors = None
        # (the policy it was built for, its native critic or None, whether it is a Q-net)
        self._critic: tuple[Any, _MlpCritic | None, bool] | None = None

    def _native_critic(self, policy: Any) -> _MlpCritic | None:
        return self._critic_of(policy)[0]

    def _critic_of(self, policy: Any) -> tuple[_MlpCritic | None, bool]:
        """The native critic of ``policy`` (or ``None``) and whether it gives Q-values.

        Both are kept per policy object: ``hasattr`` on a torch module that lacks the
        attribute raises and catches an exception inside ``nn.Module``, a few µs a step.
        """
        cached = self._critic
        if cached is None or cached[0] is not policy or (cached[1] and not cached[1].current()):
            cached = self._critic = (policy, _MlpCritic.of(policy), hasattr(policy, "q_net"))
        return cached[1], cached[2]

    @property
    def native(self) -> bool:
        """Whether calls evaluate the current policy's critic natively (not through torch)."""
        return self.fast and self._native_critic(self.model.policy) is not None

    def __call__(self, obs: ObsBatch) -> npt.NDArray[Any]:
        """Q(s, ·) ``(B, num_actions)`` with a Q-network, else V(s) ``(B,)``."""
        policy = self.model.policy
        critic, q = self._critic_of(policy) if self.fast else (None, hasattr(policy, "q_net"))
        if critic is not None:
            out = critic(obs)
            return out if q else out.reshape(-1)
        tensor, _ = policy.obs_to_tensor(obs)
        with self._no_grad():
            if q:
                return np.asarray(policy.q_net(tensor).cpu().numpy(), dtype=np.float64)
            values = policy.predict_values(tensor)
        return np.asarray(values.cpu().numpy(), dtype=np.float64).reshape(-1)

    def version(self) -> tuple[Any, ...]:
        """Changes whenever the values may have changed.

        It is made of the policy's identity, its training mode and the ids, in-place
        version counters and storage pointers of its parameters and buffers: every
        optimizer step (and ``set_parameters`` / ``load_state_dict``) bumps a counter, and
        giving a tensor new storage (``p.data = ...``) moves its pointer. Not seen: an
        in-place change through the ``.data`` alias (``p.data.add_(...)``, whose counter
        is not ``p``'s) and a submodule replaced inside the same policy object (the list
        of tensors is taken once per policy object).
        """
        policy = self.model.policy
        cached = self._tensors
        if cached is None or cached[0] is not policy:
            # Walking the modules is most of the cost: done once per policy object (its
            # parameters are updated in place; a new policy object is walked again).
            tensors = tuple(itertools.chain(policy.parameters(), policy.buffers()))
            cached = self._tensors = (policy, tensors, tuple(id(t) for t in tensors))
        _, tensors, ids = cached
        state = tuple([(t._version, t.data_ptr()) for t in tensors])
        return (id(policy), policy.training, ids, state)


def model_value_fn(model: Any, *, fast: bool = True) -> ModelValueFn:
    """Return a ``value_fn`` computing a Stable-Baselines3 model's own value estimates.

    - Models with a Q-network (``DQN``: ``model.policy.q_net``) give Q(s, ·); the server
      takes V(s) = max_a Q(s, a).
    - Actor-critic models (``A2C``, ``PPO``: ``model.policy.predict_values``) give V(s).

    With ``fast`` (the default), a critic that is a plain MLP (``MlpPolicy`` on a ``Box``
    observation space: ``FlattenExtractor``, ``Linear`` layers, ``Tanh``/``ReLU``; float32
    on the CPU) is evaluated in the native extension on views of the model's own
    parameters, which follow every training step: 10-30x cheaper per call than a torch
    forward pass, with the same values up to float32 rounding (~1e-7 relative). Any other
    policy, and ``fast=False``, goes through torch: observations preprocessed exactly as
    the policy does (``obs_to_tensor``), under ``torch.no_grad()``. The function has a
    ``version()`` method, so :class:`ShapedVecEnv` evaluates it once per observation.

    Raises:
        TypeError: The model's policy has neither ``q_net`` nor ``predict_values``.
    """
    return ModelValueFn(model, fast=fast)


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
        env: Any = self.training_env
        while self.env is None and isinstance(env, VecEnvWrapper):
            if isinstance(env, ShapedVecEnv):
                self.env = env
            env = env.venv
        if self.env is None:
            raise ValueError(
                "ShapingLogger: the model's env contains no ShapedVecEnv; pass it: "
                "ShapingLogger(env)"
            )
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
