"""The synchronous shaping session: one stream driving a vector of environments.

The session is a thin front of the native extension (``tamrm._native``): this module
checks each argument's type and shape (a fast path for arrays that already have the
canonical dtype and shape, the checks of :mod:`tamrm._batch` otherwise) and turns the
answer into a :class:`StepResult`; the per-entry checks, the episode state, and the
round trip (with the GIL released) are Rust. The same class serves
:class:`tamrm.Client` (a ``Shape`` stream to a server) and :class:`tamrm.Engine` (the
session layer in-process).
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Mapping
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from tamrm import _bridge
from tamrm._batch import (
    abandon_ids,
    checked_actions,
    checked_env_ids,
    checked_flags,
    checked_real,
    checked_scores,
)
from tamrm._closing import Closing
from tamrm._errors import SessionClosed, TamrmError, from_native
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._types import StepResult, Task, TaskConfig

__all__ = ["Session", "Transport"]

_T = TypeVar("_T")
_I64 = np.dtype(np.int64)
_F64 = np.dtype(np.float64)
_F32 = np.dtype(np.float32)
_BOOL = np.dtype(np.bool_)
_REALS = (_F64, _F32)


class Transport(Protocol):
    """What a session opens its stream on: ``tamrm._native.Channel`` or ``Engine``."""

    def open(self, task_id: str, num_envs: int, client_id: str) -> _bridge.NativeStream:
        """Open a stream (raises ``_bridge.StatusError``)."""
        ...


def _reals(name: str, value: object, shape: tuple[int, ...]) -> npt.NDArray[np.floating[Any]]:
    """``value`` as a float64/float32 array of ``shape`` (checked)."""
    if type(value) is np.ndarray and value.dtype in _REALS and value.shape == shape:
        return value
    return checked_real(name, value, shape)


def _flags(name: str, value: object, size: int) -> npt.NDArray[np.bool_] | None:
    if value is None:
        return None
    if type(value) is np.ndarray and value.dtype == _BOOL and value.shape == (size,):
        return value
    return checked_flags(name, value, size)


class Session(Closing):
    """One open stream shaping ``num_envs`` environments of one task.

    Create it with :meth:`tamrm.Client.session` (a ``Shape`` stream to a server, or with
    ``local=True`` a local session: shaped in this process against a followed copy of
    the server's pool, SPEC §13) or :meth:`tamrm.Engine.session` (in-process) and use it
    as a context manager; each :meth:`step` is one batch, answered before it returns. A
    session is not thread-safe: use one per thread (several sessions may shape on the
    same task at once). A session of a :class:`tamrm.Client` pickles as a new session of
    the same task (local or not, as it was) on (the unpickled copy of) its client, e.g.
    in a ``SubprocVecEnv`` worker.

    Attributes:
        task_id: The task shaped.
        num_envs: Number of environments (rows of a full step).
        task: The task as it was when the stream opened (its ``config`` tells whether
            actions are discrete).
    """

    task_id: str
    num_envs: int
    task: Task
    #: Set on a session made by unpickling: nobody else holds it, its wrapper owns it.
    _unpickled: bool = False
    _local: bool = False

    def __init__(self, client: Any, task_id: str, num_envs: int, *, local: bool = False) -> None:
        """Check the arguments and open the stream.

        ``local=True`` opens a local session (SPEC §13) on a transport that follows the
        server's pool (``tamrm._native.Channel.follow``) instead of a ``Shape`` stream.

        Raises:
            TypeError, ValueError: ``task_id``, ``num_envs`` or ``local`` is not valid,
                or ``local=True`` on a transport without local sessions (an engine).
            TaskNotFound: The task does not exist.
            InvalidArgument: The server rejected ``num_envs`` or the id.
        """
        if not isinstance(local, bool):
            raise TypeError(f"local must be a bool, got {type(local).__name__}")
        if not isinstance(task_id, str):
            raise TypeError(f"task_id must be a str, got {type(task_id).__name__}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {type(num_envs).__name__}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if num_envs > 2**32 - 1:
            raise ValueError(f"num_envs must be < 2**32, got {num_envs}")
        transport: Transport = client._transport
        follow: Callable[[str, int, str], _bridge.NativeStream] | None = None
        if local:
            follow = getattr(transport, "follow", None)
            if follow is None:
                raise TypeError(
                    "local=True is for a tamrm.Client (it follows a server's pool); "
                    f"the sessions of {type(client).__name__} shape in-process already"
                )
        self.task_id = task_id
        self.num_envs = int(num_envs)
        self._local = local
        self._client = client
        self._error: BaseException | None = None
        opener = transport.open if follow is None else follow
        try:
            self._native = opener(task_id, self.num_envs, uuid.uuid4().hex)
        except _bridge.StatusError as exc:
            raise from_native(exc) from None
        self.task = Task._from_pb(pb.Task.FromString(self._native.opened))
        self._config: TaskConfig = self.task.config
        self._all_rows = np.arange(self.num_envs, dtype=np.int64)

    def __deepcopy__(self, memo: dict[int, object]) -> Session:
        # A handle on a stream: copies of a wrapper's recorded arguments (gymnasium's
        # ``env.spec``) refer to the same session.
        return self

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled as "a session of this task on this client": unpickling (in a
        # SubprocVecEnv / AsyncVectorEnv worker) connects the pickled client and opens a
        # new session there, which the worker's wrapper then owns.
        return (_reopen, (self._client, self.task_id, self.num_envs, self._local))

    @property
    def local(self) -> bool:
        """Whether this is a local session (SPEC §13).

        A local session shapes its steps in this process against a copy of the server's
        pool that follows it, and sends only its episode ends.
        """
        return self._local

    @property
    def config(self) -> TaskConfig:
        """The task's resolved configuration, as returned when the stream opened."""
        return self._config

    @property
    def closed(self) -> bool:
        """Whether the stream is closed (by :meth:`close` or by a server error)."""
        return self._native.closed

    @property
    def pool_version(self) -> int:
        """The task's pool version after the last answered batch (or at open)."""
        return self._native.pool_version

    @property
    def episode_steps(self) -> npt.NDArray[np.int64]:
        """Per environment, the steps sent so far in its current (unfinished) episode."""
        return self._native.episode_steps()

    @property
    def episodes_in_progress(self) -> npt.NDArray[np.bool_]:
        """Per environment, whether an episode has been started and not yet ended."""
        return np.greater(self._native.episode_steps(), 0)

    def _check_open(self) -> None:
        if self._native.closed:
            err = SessionClosed(f"the session on task {self.task_id!r} is closed")
            raise err from self._error

    def step(
        self,
        actions: npt.ArrayLike,
        rewards: npt.ArrayLike,
        terminated: npt.ArrayLike | None = None,
        truncated: npt.ArrayLike | None = None,
        *,
        values: npt.ArrayLike | None = None,
        next_values: npt.ArrayLike | None = None,
        q_values: npt.ArrayLike | None = None,
        next_q_values: npt.ArrayLike | None = None,
        episode_scores: npt.ArrayLike | Mapping[int, float] | None = None,
        env_ids: npt.ArrayLike | None = None,
    ) -> StepResult:
        """Shape one vector step: one row per environment (or per entry of ``env_ids``).

        Args:
            actions: The actions taken: integers of shape ``(B,)`` for a discrete task,
                reals of shape ``(B, action_dim)`` for a continuous one.
            rewards: The environment rewards R, shape ``(B,)``.
            terminated: Booleans ``(B,)``: the step reached a terminal state (V(s') is
                taken as 0). ``None`` means all false.
            truncated: Booleans ``(B,)``: the step hit a time limit (the sent V(s') is
                used). ``None`` means all false.
            values: V(s) per row, shape ``(B,)``; give together with ``next_values``.
            next_values: V(s') per row, shape ``(B,)`` (the real last observation's
                value on a truncation, not the reset observation's).
            q_values: Q(s, ·) per row, shape ``(B, num_actions)``, discrete tasks only;
                give together with ``next_q_values``, not with ``values``.
            next_q_values: Q(s', ·), shape ``(B, num_actions)``.
            episode_scores: Episode scores for rows that end an episode, either as an
                array ``(B,)`` (entries on rows that do not end an episode, and NaN
                entries, are ignored) or as a mapping ``{row: score}``. Rows without a
                score use the sum of the episode's environment rewards.
            env_ids: Optional integers ``(B,)``: the environment of each row, for
                sending a subset of the environments (e.g. skipping autoreset steps).
                ``None`` means row i is environment i and B = ``num_envs``.

        Returns:
            The shaped rewards and their parts, one row per row sent. With ``B == 0``
            nothing is sent and an empty result is returned.

        Raises:
            TypeError, ValueError: An argument has the wrong dtype or shape (nothing was
                sent; the session stays usable).
            InvalidArgument: A number is not finite or too large for its 32-bit field
                (caught before sending: nothing was sent, the session stays usable), or
                the server rejected the batch (e.g. a score on a non-final entry).
            TaskNotFound: The task was deleted.
            SessionClosed: The session was closed or an earlier step failed.

            A batch the server rejects (``InvalidArgument``) changes nothing (SPEC §8):
            the session goes on (a remote session re-opens its stream, resuming every
            episode in progress, SPEC §9), so the next step goes on as if the bad batch
            had never been sent. After any other server error the session is closed;
            open a new one (or call :meth:`restart`) to continue.
        """
        self._check_open()
        config = self._config
        if env_ids is None:
            ids = None
            rows = self._all_rows
            size = self.num_envs
        else:
            ids = checked_env_ids(env_ids, self.num_envs)
            assert ids is not None
            rows = ids
            size = int(ids.shape[0])
        rew = rewards
        if not (type(rew) is np.ndarray and rew.dtype == _F64 and rew.shape == (size,)):
            rew = checked_real("rewards", rewards, (size,))
        term = _flags("terminated", terminated, size)
        trunc = _flags("truncated", truncated, size)
        act = actions
        if config.discrete:
            if not (type(act) is np.ndarray and act.dtype == _I64 and act.shape == (size,)):
                act = checked_actions(config, actions, size)
        elif not (
            type(act) is np.ndarray
            and act.dtype in _REALS
            and act.shape == (size, config.action_dim)
        ):
            act = checked_actions(config, actions, size)
        v = nv = q = nq = None
        if values is not None or next_values is not None:
            if values is None or next_values is None:
                raise TypeError("values and next_values must be given together")
            if q_values is not None or next_q_values is not None:
                raise TypeError(
                    "give either values/next_values or q_values/next_q_values, not both"
                )
            v = _reals("values", values, (size,))
            nv = _reals("next_values", next_values, (size,))
        elif q_values is not None or next_q_values is not None:
            if q_values is None or next_q_values is None:
                raise TypeError("q_values and next_q_values must be given together")
            if not config.discrete:
                raise ValueError("q_values are only accepted by discrete tasks (num_actions > 0)")
            shape = (size, config.num_actions)
            q = _reals("q_values", q_values, shape)
            nq = _reals("next_q_values", next_q_values, shape)
        score_rows = score_values = None
        if episode_scores is not None:
            done = np.zeros(size, dtype=np.bool_)
            if term is not None:
                done |= term
            if trunc is not None:
                done |= trunc
            scores = checked_scores(episode_scores, done)
            score_rows = np.fromiter(scores.keys(), dtype=np.int64, count=len(scores))
            score_values = np.fromiter(scores.values(), dtype=np.float64, count=len(scores))
        if size == 0:
            # Nothing is sent; pending abandons wait for a batch with entries.
            return StepResult._empty(self._native.pool_version)
        answer = self._call(
            self._native.step, ids, act, rew, term, trunc, v, nv, q, nq, score_rows, score_values
        )
        parts, steps, active, pool_version = answer
        return StepResult(parts[0], parts[1], parts[2], steps, active, pool_version, rows)

    def _call(self, method: Callable[..., _T], *args: Any) -> _T:
        """A native step call, its failures turned into this session's errors."""
        try:
            return method(*args)
        except _bridge.StatusError as exc:
            raise self._failed(exc) from None
        except KeyboardInterrupt:
            self._interrupted()
            raise

    def _failed(self, exc: _bridge.StatusError) -> TamrmError:
        """The error to raise for a failed native step call (kept if it closed the session)."""
        err = from_native(exc)
        if self._native.closed:
            self._error = err
        return err

    def _interrupted(self) -> None:
        """Record that a step was interrupted (Ctrl-C): the stream is gone."""
        self._error = SessionClosed(f"the session on task {self.task_id!r} was interrupted")

    def abandon(self, env_ids: npt.ArrayLike) -> None:
        """Drop the current episodes of ``env_ids`` without offering them to the pool.

        For an environment that crashed or was reset by hand in the middle of an episode
        (SPEC v1.1 §12): its next step is step t = 0 of a new episode, and the unfinished
        episode is never stored; the other environments' episodes go on. The wrappers
        call this when an environment is reset before its episode ended.

        Nothing is sent by this call: the ids travel in the ``abandon`` field of the next
        batch that has entries, which the server applies before that batch's entries.
        ``episodes_in_progress`` and ``episode_steps`` reflect it at once. Abandoning an
        environment again before that batch is a no-op.

        Args:
            env_ids: Integer environment ids (or one id), each ``< num_envs``, none twice.

        Raises:
            TypeError: ``env_ids`` does not hold integers.
            ValueError: An id is out of range, listed twice, or ``env_ids`` is not 1-D.
                Nothing is recorded.
            SessionClosed: The session is closed.
        """
        self._check_open()
        self._native.abandon(abandon_ids(env_ids, self.num_envs))

    def restart(self) -> None:
        """Close the stream and open a new one on the same task.

        Episodes in progress are discarded (SPEC §6: an episode whose stream ends before
        its final step is not stored); every environment starts a new episode at its
        next step. To drop only some environments' episodes, use :meth:`abandon`.
        """
        self._native.close()
        try:
            self._native.reopen()
        except _bridge.StatusError as exc:
            raise from_native(exc) from None
        self._error = None

    def close(self) -> None:
        """End the stream (idempotent); episodes still in progress are discarded.

        While a ``KeyboardInterrupt`` unwinds, the stream is dropped at once.
        """
        self._native.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        local = " local" if self._local else ""
        return f"<tamrm.Session task_id={self.task_id!r} num_envs={self.num_envs}{local} {state}>"


def _reopen(client: Any, task_id: str, num_envs: int, local: bool = False) -> Session:
    """Unpickle a session: a new one (local if it was) on (the unpickled copy of) its client."""
    session: Session = client.session(task_id, num_envs, local=local)
    session._unpickled = True
    return session
