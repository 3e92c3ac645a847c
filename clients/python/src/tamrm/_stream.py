"""A ``Shape`` stream's client side without I/O: what the sync and asyncio sessions share.

:class:`SessionCore` builds every request of the stream (``Open``, each ``StepBatch`` with
its pending abandons), decodes every answer and keeps the per-environment episode state.
:class:`tamrm.Session` and :class:`tamrm.aio.AsyncSession` subclass it and only move the
messages (blocking or awaiting).
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from typing import Any, Generic, TypeVar

import grpc
import numpy as np
import numpy.typing as npt

from tamrm._batch import PreparedBatch, StepInput, abandon_ids, prepare_batch
from tamrm._errors import SessionClosed, TamrmError
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._proto.tamrm.v1 import shaping_pb2_grpc as pb_grpc
from tamrm._types import StepResult, Task, TaskConfig

__all__ = ["SessionCore"]

_R = TypeVar("_R")


class SessionCore(Generic[_R]):
    """A ``Shape`` stream's client side without I/O, shared by the sync and asyncio sessions.

    It builds the requests (``Open``, each ``StepBatch``), decodes the answers and keeps
    the per-environment state. The two front-ends only move the messages:
    :class:`Session` (``_R`` = :class:`StepResult`) blocks, :class:`tamrm.aio.AsyncSession`
    (``_R`` = an awaitable of it) awaits; each implements :meth:`_exchange`.
    """

    task_id: str
    num_envs: int
    task: Task
    _episode_steps: npt.NDArray[np.int64]
    _pool_version: int
    _closed: bool
    _error: BaseException | None
    #: Set on a session made by unpickling: nobody else holds it, its wrapper owns it.
    _unpickled: bool = False

    def __init__(self, client: Any, task_id: str, num_envs: int) -> None:
        """Check the arguments and start the session (see :meth:`_start`).

        Raises:
            TypeError, ValueError: ``task_id`` or ``num_envs`` is not valid.
            TaskNotFound: (sync session) The task does not exist.
            InvalidArgument: (sync session) The server rejected ``num_envs`` or the id.
        """
        if not isinstance(task_id, str):
            raise TypeError(f"task_id must be a str, got {type(task_id).__name__}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {type(num_envs).__name__}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.task_id = task_id
        self.num_envs = int(num_envs)
        self._episode_steps = np.zeros(self.num_envs, dtype=np.int64)
        self._abandon_pending: list[int] = []
        self._abandon_unconfirmed = np.zeros(self.num_envs, dtype=np.bool_)
        self._pool_version = 0
        self._closed = True
        self._error = None
        # What resuming the episodes on a new stream takes (SPEC §9): per env, the current
        # episode's actions and reward sum, and the number of episodes it has ended; the
        # client id makes a re-opened stream's episode ends count once.
        self._client_id = uuid.uuid4().hex
        self._episode_actions: list[list[Any]] = [[] for _ in range(self.num_envs)]
        self._reward_sums = np.zeros(self.num_envs, dtype=np.float64)
        self._episodes_ended = np.zeros(self.num_envs, dtype=np.int64)
        self._client = client
        self._stub: pb_grpc.ShapingStub = client._stub
        self._metadata: tuple[tuple[str, str], ...] | None = client._metadata
        self._start()

    def __deepcopy__(self, memo: dict[int, object]) -> SessionCore[_R]:
        # A handle on a stream: copies of a wrapper's recorded arguments (gymnasium's
        # ``env.spec``) refer to the same session.
        return self

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled as "a session of this task on this client": unpickling (in a
        # SubprocVecEnv / AsyncVectorEnv worker) connects the pickled client and opens a
        # new session there, which the worker's wrapper then owns.
        return (_reopen, (self._client, self.task_id, self.num_envs))

    def _start(self) -> None:
        """Front-end hook run at the end of ``__init__`` (the sync session opens here)."""
        raise NotImplementedError

    @property
    def config(self) -> TaskConfig:
        """The task's resolved configuration, as returned when the stream opened."""
        return self.task.config

    @property
    def closed(self) -> bool:
        """Whether the stream is closed (by :meth:`close` or by a server error)."""
        return self._closed

    @property
    def pool_version(self) -> int:
        """The task's pool version after the last answered batch (or at open)."""
        return self._pool_version

    @property
    def episode_steps(self) -> npt.NDArray[np.int64]:
        """Per environment, the steps sent so far in its current (unfinished) episode."""
        steps: npt.NDArray[np.int64] = self._episode_steps.copy()
        return steps

    @property
    def episodes_in_progress(self) -> npt.NDArray[np.bool_]:
        """Per environment, whether an episode has been started and not yet ended."""
        return np.greater(self._episode_steps, 0)

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
    ) -> _R:
        """Shape one vector step; arguments, result and errors as :meth:`tamrm.Session.step`.

        On an :class:`tamrm.aio.AsyncSession` this returns an awaitable (``await
        session.step(...)``); the arguments are checked when it is awaited.
        """
        return self._exchange(
            StepInput(
                actions,
                rewards,
                terminated,
                truncated,
                values,
                next_values,
                q_values,
                next_q_values,
                episode_scores,
                env_ids,
            )
        )

    def abandon(self, env_ids: npt.ArrayLike) -> None:
        """Drop the current episodes of ``env_ids`` without offering them to the pool.

        For an environment that crashed or was reset by hand in the middle of an episode
        (SPEC v1.1 §12): its next step is step t = 0 of a new episode, and the unfinished
        episode is never stored; the other environments' episodes go on. The wrappers
        call this when an environment is reset before its episode ended.

        Nothing is sent by this call (it is a plain method on the asyncio session too):
        the ids travel in the ``abandon`` field of the next ``StepBatch`` that has
        entries, which the server applies before that batch's entries. This saves a round
        trip per reset and is equivalent, since an abandon changes neither the pool nor
        the task's counters. ``episodes_in_progress`` and ``episode_steps`` reflect it at
        once. Abandoning an environment again before that batch is a no-op.

        Args:
            env_ids: Integer environment ids (or one id), each ``< num_envs``, none twice.

        Raises:
            TypeError: ``env_ids`` does not hold integers.
            ValueError: An id is out of range, listed twice, or ``env_ids`` is not 1-D.
                Nothing is recorded.
            SessionClosed: The session is closed.
        """
        self._check_open()
        ids = abandon_ids(env_ids, self.num_envs)
        for env in ids:
            if env not in self._abandon_pending:
                self._abandon_pending.append(env)
            self._episode_actions[env] = []
        self._episode_steps[ids] = 0
        self._reward_sums[ids] = 0.0

    def _exchange(self, step: StepInput) -> _R:
        """Send the step's batch (from :meth:`_prepare`) and decode the answer (:meth:`_shaped`)."""
        raise NotImplementedError

    # -- the protocol, without I/O ---------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            err = SessionClosed(f"the session on task {self.task_id!r} is closed")
            raise err from self._error

    def _open_request(self) -> pb.ShapeRequest:
        """``Open``, resuming every env's current episode (none on a first open, SPEC §9).

        Envs that have ended episodes are listed even between episodes, so that the
        server goes on numbering their episode ends (``EnvResume.episode``).
        """
        resume = []
        for env in range(self.num_envs):
            actions = self._episode_actions[env]
            if not actions and not self._episodes_ended[env]:
                continue
            item = pb.EnvResume(
                env_id=env,
                reward_sum=float(self._reward_sums[env]),
                episode=int(self._episodes_ended[env]),
            )
            if actions and np.ndim(actions[0]) > 0:
                item.action_vectors.extend(np.concatenate(actions).tolist())
            else:
                item.actions.extend(actions)
            resume.append(item)
        return pb.ShapeRequest(
            open=pb.Open(
                task_id=self.task_id,
                num_envs=self.num_envs,
                client_id=self._client_id,
                resume=resume,
            )
        )

    def _rejected(self, err: TamrmError) -> bool:
        """Whether ``err`` rejected one batch and changed nothing else (SPEC §8).

        The front-end then re-opens the stream, resuming every episode, before raising it.
        """
        return bool(err.code == grpc.StatusCode.INVALID_ARGUMENT)

    def _opened(self, resp: pb.ShapeResponse) -> None:
        if resp.WhichOneof("kind") != "opened":
            raise TamrmError(f"expected 'opened' as the first Shape response, got {resp}")
        self.task = Task._from_pb(resp.opened)
        self._pool_version = self.task.stats.pool_version
        # The resumed episodes go on where they were; the others start anew.
        self._episode_steps[:] = [len(actions) for actions in self._episode_actions]
        self._abandon_pending.clear()  # sent envs were not resumed: they start anew
        self._abandon_unconfirmed[:] = False
        self._closed = False
        self._error = None

    def _prepare(self, step: StepInput) -> PreparedBatch | StepResult:
        """The batch to send for ``step``, or the (empty) result when there is nothing to send.

        Raises:
            SessionClosed: The session is closed.
            TypeError, ValueError: See :meth:`step`.
        """
        self._check_open()
        prepared = prepare_batch(self.task.config, self.num_envs, step)
        if prepared.size == 0:
            # Nothing is sent; pending abandons wait for a batch with entries.
            return StepResult._empty(self._pool_version)
        prepared.request.steps.abandon.extend(self._abandon_pending)
        # Sent now: the answer must show these envs starting over (_confirm_abandons).
        self._abandon_unconfirmed[self._abandon_pending] = True
        return prepared

    def _shaped(self, resp: pb.ShapeResponse, prepared: PreparedBatch) -> StepResult:
        """Decode the answer to ``prepared`` and update the per-environment state.

        Raises:
            TamrmError: The answer does not match the batch (the caller ends the stream).
        """
        env_ids, done = prepared.env_ids, prepared.done
        if resp.WhichOneof("kind") != "shaped":
            raise TamrmError(f"expected a 'shaped' Shape response, got {resp.WhichOneof('kind')}")
        result = StepResult._from_pb(resp.shaped, env_ids)
        if len(result) != env_ids.shape[0] or result.steps.shape[0] != env_ids.shape[0]:
            raise TamrmError(
                f"the server answered {len(result)} entries for a batch of {env_ids.shape[0]}"
            )
        del self._abandon_pending[: len(prepared.request.steps.abandon)]
        self._confirm_abandons(result)
        self._track(prepared)
        # Rows of one env come in order, so the last assignment wins as it should.
        self._episode_steps[env_ids] = result.steps + 1
        self._episode_steps[env_ids[done]] = 0
        self._episode_steps[self._abandon_pending] = 0  # abandoned since this batch was sent
        self._pool_version = result.pool_version
        return result

    def _track(self, prepared: PreparedBatch) -> None:
        """Record an answered batch's actions and rewards in each env's current episode."""
        actions = prepared.actions.tolist()
        for row, env in enumerate(prepared.env_ids.tolist()):
            if prepared.done[row]:
                self._episode_actions[env] = []
                self._reward_sums[env] = 0.0
                self._episodes_ended[env] += 1
            else:
                self._episode_actions[env].append(actions[row])
                self._reward_sums[env] += prepared.rewards[row]

    def _confirm_abandons(self, result: StepResult) -> None:
        """Check that the first entry of each abandoned env started a new episode.

        A server older than SPEC v1.1 ignores ``StepBatch.abandon`` (an unknown field) and
        would go on with the dropped episode: fail loudly instead.

        Raises:
            TamrmError: ``UNIMPLEMENTED``, the server did not abandon the episode.
        """
        if not self._abandon_unconfirmed.any():
            return
        envs, first = np.unique(result.env_ids, return_index=True)
        for env, row in zip(envs.tolist(), first.tolist(), strict=True):
            if self._abandon_unconfirmed[env] and result.steps[row] != 0:
                raise TamrmError(
                    f"the server ignored StepBatch.abandon (SPEC v1.1 §12): env {env} went on "
                    f"with its abandoned episode at step {result.steps[row]}; upgrade the server",
                    grpc.StatusCode.UNIMPLEMENTED,
                )
        self._abandon_unconfirmed[envs] = False

    def _failed(self, err: BaseException) -> None:
        """Record that the stream ended with ``err``."""
        self._closed = True
        self._error = err

    def _closing(self) -> bool:
        """Mark the session closed; return whether it was open (so there is a stream to end)."""
        if self._closed:
            return False
        self._closed = True
        self._episode_steps[:] = 0
        # A closed stream's episodes are discarded (SPEC §6): nothing to resume.
        self._episode_actions = [[] for _ in range(self.num_envs)]
        self._reward_sums[:] = 0.0
        return True


def _reopen(client: Any, task_id: str, num_envs: int) -> Any:
    """Unpickle a session: a new one on (the unpickled copy of) its client."""
    session = client.session(task_id, num_envs)
    session._unpickled = True
    return session
