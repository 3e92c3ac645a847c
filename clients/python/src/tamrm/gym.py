"""gymnasium wrappers that replace the environment reward with the shaped reward.

Shaping an existing gymnasium loop is a three-line change::

    client = tamrm.Client("127.0.0.1:50051")
    client.create_task("cartpole", num_actions=2)
    env = tamrm.gym.ShapedReward(gym.make("CartPole-v1"), client.session("cartpole"))

or for a vector environment::

    envs = gym.make_vec("CartPole-v1", num_envs=8)
    envs = tamrm.gym.VectorShapedReward(envs, client.session("cartpole", envs.num_envs))

The original reward and the shaping parts are put into ``info`` under
``original_reward``, ``knn_reward``, ``potential``, ``shaping_step``, ``knn_active`` and
``pool_version`` (for vector environments: arrays with ``_``-prefixed masks, following
gymnasium's vector info convention). ``terminated`` and ``truncated`` are passed through
unchanged and sent to the server separately: a terminated step has V(s') = 0, a
truncated one uses the value of the real last observation (SPEC §4).
"""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium.utils import RecordConstructorArgs
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper

from tamrm._session import Session
from tamrm._types import StepResult, TaskConfig
from tamrm._values import ObsBatch, ValueFn, copy_obs, select_obs, set_obs_row, value_kwargs
from tamrm._wrapping import check_action_space, check_session, close_session

__all__ = ["INFO_KEYS", "ShapedReward", "ValueFn", "VectorShapedReward"]

#: The ``info`` keys the wrappers add.
INFO_KEYS: tuple[str, ...] = (
    "original_reward",
    "knn_reward",
    "potential",
    "shaping_step",
    "knn_active",
    "pool_version",
)


def _single_action(action: npt.ArrayLike, config: TaskConfig) -> npt.NDArray[np.generic]:
    arr = np.asarray(action)
    if config.discrete:
        return arr.reshape(1)
    return arr.reshape(1, config.action_dim)


class ShapedReward(gymnasium.Wrapper[Any, Any, Any, Any], RecordConstructorArgs):
    """Shape the reward of a single gymnasium environment through a tamrm session.

    Each ``step`` sends one entry (action, reward, terminated, truncated and, with a
    ``value_fn``, V or Q of the previous and the new observation) and returns the shaped
    reward. A ``reset`` in the middle of an episode abandons it (:meth:`tamrm.Session.abandon`)
    so that the server drops the unfinished episode rather than continuing it.

    Args:
        env: The environment. Its action space must match the task: ``Discrete(n)`` for
            ``num_actions=n``, a ``Box`` of ``action_dim`` elements otherwise.
        session: An open session (``client.session(task_id)``); the wrapper uses its
            environment ``env_id``.
        value_fn: Optional ``value_fn(obs_batch)`` returning V(s) ``(B,)`` or Q(s, ·)
            ``(B, num_actions)`` for a batch of observations; without it F = 0.
        env_id: Which of the session's environments this wrapper drives.
        score_key: Optional ``info`` key holding the episode score S (SPEC §6) on the step
            that ends an episode, e.g. ``100 / steps`` in a sparse maze. An ending step
            whose ``info`` lacks the key (e.g. a ``TimeLimit`` truncation) gets the
            server's default, the sum of the episode's environment rewards.
        close_session: Whether :meth:`close` closes ``session``. By default (``None``) it
            does, unless the session is open in a ``with`` block (which then owns it):
            ``ShapedReward(env, client.session(task_id))`` hands the session over.
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        session: Session,
        value_fn: ValueFn | None = None,
        *,
        env_id: int = 0,
        score_key: str | None = None,
        close_session: bool | None = None,
    ) -> None:
        # Recorded for ``env.spec`` (``env.spec.make()``, gymnasium's ``check_env``): the
        # same session (a session deep-copies as itself), borrowed by the copies.
        RecordConstructorArgs.__init__(
            self,
            session=session,
            value_fn=value_fn,
            env_id=env_id,
            score_key=score_key,
            close_session=False,
            _disable_deepcopy=True,
        )
        gymnasium.Wrapper.__init__(self, env)
        if not 0 <= env_id < session.num_envs:
            raise ValueError(f"env_id {env_id} is not < session.num_envs={session.num_envs}")
        check_action_space(env.action_space, session.config)
        self.session = session
        self.value_fn = value_fn
        self.env_id = env_id
        self.score_key = score_key
        self.close_session = close_session
        self._env_ids = None if session.num_envs == 1 else np.array([env_id], dtype=np.int64)
        self._obs: Any = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset the environment; abandon its episode if one was in progress (SPEC §12)."""
        obs, info = self.env.reset(seed=seed, options=options)
        if self.session.episodes_in_progress[self.env_id]:
            self.session.abandon([self.env_id])
        self._obs = obs
        return obs, info

    def close(self) -> None:
        """Close the environment, then the session if the wrapper owns it (``close_session``)."""
        try:
            super().close()  # type: ignore[no-untyped-call, unused-ignore]
        finally:
            close_session(self.session, self.close_session)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Step the environment and return the shaped reward (the original is in ``info``)."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        values: dict[str, npt.NDArray[np.float64]] = {}
        if self.value_fn is not None:
            if self._obs is None:
                raise RuntimeError("call reset() before step()")
            values = value_kwargs(
                self.value_fn,
                np.expand_dims(np.asarray(self._obs), 0),
                np.expand_dims(np.asarray(obs), 0),
                1,
            )
        scores = None
        if self.score_key is not None and (terminated or truncated) and self.score_key in info:
            scores = {0: float(info[self.score_key])}
        result = self.session.step(
            _single_action(action, self.session.config),
            np.array([float(reward)]),
            np.array([bool(terminated)]),
            np.array([bool(truncated)]),
            env_ids=self._env_ids,
            episode_scores=scores,
            **values,
        )
        self._obs = obs
        info = dict(info)
        info["original_reward"] = float(reward)
        info["knn_reward"] = float(result.knn_rewards[0])
        info["potential"] = float(result.potentials[0])
        info["shaping_step"] = int(result.steps[0])
        info["knn_active"] = bool(result.knn_active[0])
        info["pool_version"] = result.pool_version
        return obs, float(result.rewards[0]), terminated, truncated, info


def _autoreset_mode(env: VectorEnv[Any, Any, Any]) -> AutoresetMode:
    mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
    if isinstance(mode, AutoresetMode):
        return mode
    if isinstance(mode, str):
        for member in AutoresetMode:
            if mode in (member.value, member.name):
                return member
    raise ValueError(f"unknown autoreset_mode {mode!r}")


class VectorShapedReward(VectorWrapper):
    """Shape the rewards of a gymnasium vector environment through one tamrm session.

    One ``step`` of the vector environment is one round trip on the session. Both
    autoreset modes are handled:

    - ``NEXT_STEP`` (gymnasium's default): the step after an episode ended only resets
      that sub-environment (its reward is 0 and it is not an environment step), so it is
      not sent; the ``done`` step's observation is the real last one.
    - ``SAME_STEP``: every step is sent; the real last observation of an ended episode is
      taken from ``info["final_obs"]`` for V(s').
    - ``DISABLED``: every step is sent; reset finished sub-environments yourself.

    ``info`` gets ``original_reward``, ``knn_reward``, ``potential``, ``shaping_step``,
    ``knn_active`` and ``pool_version`` arrays with ``_``-prefixed masks telling which
    sub-environments were shaped on this step.

    Args:
        env: The vector environment (``num_envs`` must equal ``session.num_envs``).
        session: An open session with ``num_envs`` environments.
        value_fn: Optional ``value_fn(obs_batch)`` returning V(s) ``(B,)`` or Q(s, ·)
            ``(B, num_actions)``; without it F = 0.
        score_key: Optional ``info`` key holding the episode score S of the
            sub-environments whose episode ends on this step (with ``SAME_STEP``, looked
            up in ``info["final_info"]``). Ending sub-environments without it (mask
            ``info["_" + score_key]``) get the server's default, the sum of the episode's
            environment rewards.
        close_session: Whether :meth:`close` closes ``session``. By default (``None``) it
            does, unless the session is open in a ``with`` block (which then owns it):
            ``VectorShapedReward(envs, client.session(task_id))`` hands the session over.
    """

    def __init__(
        self,
        env: VectorEnv[Any, Any, Any],
        session: Session,
        value_fn: ValueFn | None = None,
        *,
        score_key: str | None = None,
        close_session: bool | None = None,
    ) -> None:
        super().__init__(env)
        check_session(session, env.num_envs, env.single_action_space, "the vector env")
        self.session = session
        self.close_session = close_session
        self.value_fn = value_fn
        self.autoreset_mode = _autoreset_mode(env)
        self.score_key = score_key
        self._obs: ObsBatch | None = None
        self._autoreset = np.zeros(env.num_envs, dtype=np.bool_)

    # (gymnasium 1.2, which ray[rllib] pins, types VectorWrapper.reset's seed as a list too.)
    def reset(  # type: ignore[override, unused-ignore]
        self,
        *,
        seed: int | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Any, dict[str, Any]]:
        """Reset (all or, with ``options["reset_mask"]``, some) sub-environments.

        The episodes of the sub-environments reset in the middle of an episode are
        abandoned (SPEC §12: dropped, not stored); the others go on.
        """
        # Read the mask first: gymnasium's vector envs pop it from ``options``.
        mask = np.ones(self.num_envs, dtype=np.bool_)
        if options is not None and "reset_mask" in options:
            mask = np.array(options["reset_mask"], dtype=np.bool_)
        obs, info = self.env.reset(seed=seed, options=options)
        interrupted = self.session.episodes_in_progress & mask
        if interrupted.any():
            self.session.abandon(np.flatnonzero(interrupted))
        self._autoreset[mask] = False
        self._obs = obs
        return obs, info

    def close(self, **kwargs: Any) -> None:
        """Close the vector env, then the session if the wrapper owns it (``close_session``)."""
        try:
            super().close(**kwargs)
        finally:
            # gymnasium's __del__ closes a wrapper whose __init__ raised: it has no session.
            if "close_session" in self.__dict__:
                close_session(self.session, self.close_session)

    # (gymnasium 1.2 types VectorWrapper.step generically.)
    def step(  # type: ignore[override, unused-ignore]
        self, actions: npt.ArrayLike
    ) -> tuple[
        Any, npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]
    ]:
        """Step every sub-environment and return the shaped rewards."""
        obs, reward, terminated, truncated, info = self.env.step(actions)
        rewards = np.asarray(reward, dtype=np.float64)
        term = np.asarray(terminated, dtype=np.bool_)
        trunc = np.asarray(truncated, dtype=np.bool_)
        acts = np.asarray(actions)

        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            sent = ~self._autoreset
        else:
            sent = np.ones(self.num_envs, dtype=np.bool_)
        all_sent = bool(sent.all())
        rows = None if all_sent else np.flatnonzero(sent)

        values: dict[str, npt.NDArray[np.float64]] = {}
        if self.value_fn is not None:
            if self._obs is None:
                raise RuntimeError("call reset() before step()")
            next_obs = obs
            if self.autoreset_mode == AutoresetMode.SAME_STEP and "final_obs" in info:
                final_mask = np.asarray(info.get("_final_obs", term | trunc), dtype=np.bool_)
                if final_mask.any():
                    next_obs = copy_obs(obs)
                    for i in np.flatnonzero(final_mask):
                        set_obs_row(next_obs, int(i), info["final_obs"][i])
            size = self.num_envs if rows is None else int(rows.shape[0])
            values = value_kwargs(
                self.value_fn, select_obs(self._obs, rows), select_obs(next_obs, rows), size
            )

        result = self.session.step(
            acts if rows is None else acts[rows],
            rewards if rows is None else rewards[rows],
            term if rows is None else term[rows],
            trunc if rows is None else trunc[rows],
            env_ids=rows,
            episode_scores=(
                None
                if self.score_key is None
                else self._episode_scores(info, (term | trunc) & sent, rows)
            ),
            **values,
        )
        if rows is None:
            shaped = result.rewards
        else:
            shaped = rewards.copy()
            shaped[sent] = result.rewards
        info = dict(info)
        self._add_shaping_info(info, result, rewards, sent)
        self._obs = obs
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            self._autoreset = term | trunc
        return obs, shaped, term, trunc, info

    def _episode_scores(
        self,
        info: dict[str, Any],
        ending: npt.NDArray[np.bool_],
        rows: npt.NDArray[np.intp] | None,
    ) -> dict[int, float] | None:
        """``{batch row: score}`` of the ending sub-environments that report a score."""
        key = self.score_key
        if key is None or not ending.any():
            return None
        source = info
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            source = info.get("final_info", {})
        if key not in source:
            return None
        values = source[key]
        has = np.asarray(source.get(f"_{key}", ending), dtype=np.bool_) & ending
        # Batch rows are sub-environment indices, or positions in ``rows`` when only some
        # sub-environments are sent.
        position = (
            {int(env): pos for pos, env in enumerate(rows.tolist())} if rows is not None else None
        )
        return {
            int(env) if position is None else position[int(env)]: float(values[env])
            for env in np.flatnonzero(has)
        }

    def _add_shaping_info(
        self,
        info: dict[str, Any],
        result: StepResult,
        rewards: npt.NDArray[np.float64],
        sent: npt.NDArray[np.bool_],
    ) -> None:
        n = self.num_envs
        pool_version = np.full(n, result.pool_version, dtype=np.int64)
        if result.rewards.shape[0] == n:
            # Every env was sent (the usual step): the answer's columns are the info's.
            columns: dict[str, npt.NDArray[np.generic]] = {
                "original_reward": rewards.copy(),
                "knn_reward": result.knn_rewards,
                "potential": result.potentials,
                "shaping_step": result.steps,
                "knn_active": result.knn_active,
                "pool_version": pool_version,
            }
        else:
            columns = {
                "original_reward": rewards.copy(),
                "knn_reward": np.zeros(n, dtype=np.float64),
                "potential": np.zeros(n, dtype=np.float64),
                "shaping_step": np.zeros(n, dtype=np.int64),
                "knn_active": np.zeros(n, dtype=np.bool_),
                "pool_version": pool_version,
            }
            columns["knn_reward"][sent] = result.knn_rewards
            columns["potential"][sent] = result.potentials
            columns["shaping_step"][sent] = result.steps
            columns["knn_active"][sent] = result.knn_active
        # One mask array for the six keys: it says the same of each.
        mask = sent.copy()
        for key, column in columns.items():
            info[key] = column
            info[f"_{key}"] = mask
