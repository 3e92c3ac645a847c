"""The task methods of :class:`tamrm.Client` and :class:`tamrm.Engine`, written once.

:class:`TaskCalls` builds each unary call's request (:mod:`tamrm._ops`), hands its bytes
to the transport's ``_invoke`` and decodes the answer; the deadline of a call
(:data:`Timeout`, :data:`CLIENT_TIMEOUT`) is typed here.
"""

from __future__ import annotations

import enum
import functools
from typing import TYPE_CHECKING, Any, TypeVar

import numpy.typing as npt
from google.protobuf import message_factory
from google.protobuf.message import Message

from tamrm import _bridge, _pool_transfer
from tamrm import _ops as ops
from tamrm._errors import from_native
from tamrm._pool_file import PoolFileLike
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._session import Session
from tamrm._types import AddTrajectoryResult, Pool, Task, TaskOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["CLIENT_TIMEOUT", "DEFAULT_TIMEOUT", "TaskCalls", "Timeout"]

#: Default deadline, in seconds, of every unary call (not of ``Shape`` streams).
DEFAULT_TIMEOUT = 30.0


class _ClientTimeout(enum.Enum):
    TIMEOUT = "the client's timeout"


#: The default of a call's ``timeout=``: the deadline given to the client.
CLIENT_TIMEOUT = _ClientTimeout.TIMEOUT

#: A call's deadline: seconds, ``None`` for none, or :data:`CLIENT_TIMEOUT`.
Timeout = float | None | _ClientTimeout

_T = TypeVar("_T")


def _response_types() -> dict[str, type[Message]]:
    """Each ``Shaping`` method's response message class, from the proto's descriptor."""
    service = pb.DESCRIPTOR.services_by_name["Shaping"]
    return {
        m.name: message_factory.GetMessageClass(m.output_type)
        for m in service.methods
        if not m.client_streaming
    }


_RESPONSES = _response_types()


class TaskCalls:
    """The task methods of :class:`tamrm.Client` and :class:`tamrm.Engine`, written once.

    A subclass provides ``_invoke(method, request_bytes, timeout) -> response_bytes``
    (raising ``tamrm._native.StatusError``) and a ``_transport`` that opens sessions.

    Every method takes ``timeout=``: that call's deadline in seconds (``None``: none),
    by default the client's ``timeout``. When it passes, the call raises
    :class:`tamrm.DeadlineExceeded`. An :class:`tamrm.Engine` runs calls in-process and
    ignores it.
    """

    _transport: Any

    def _invoke(self, method: str, request: bytes, timeout: Timeout) -> bytes:
        raise NotImplementedError

    def _call(self, timeout: Timeout, rpc: ops.Rpc) -> Any:
        try:
            answer = self._invoke(rpc.method, rpc.request.SerializeToString(), timeout)
        except _bridge.StatusError as exc:
            raise from_native(exc) from None
        return _RESPONSES[rpc.method].FromString(answer)

    def _run(self, op: ops.Op[_T], timeout: Timeout = CLIENT_TIMEOUT) -> _T:
        return ops.run(op, functools.partial(self._call, timeout))

    # -- tasks -----------------------------------------------------------------------

    def create_task(
        self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT, **config: Unpack[TaskOptions]
    ) -> Task:
        """Create a task; keywords left out (or ``None``) take the server's defaults.

        The keywords are exactly the ``TaskConfig`` fields (:data:`tamrm.CONFIG_FIELDS`,
        typed by :class:`tamrm.TaskOptions`; SPEC §1.1): ``num_actions``, ``action_dim``,
        ``pool_capacity``, ``k``, ``start_step``, ``min_pool_size``, ``alpha``, ``beta``,
        ``gamma``, ``max_trajectory_len``, ``gate_potential``, ``require_score_spread``.

        Exactly one of ``num_actions`` (discrete actions ``0..n-1``) and ``action_dim``
        (continuous action vectors) must be given. Creating an existing task with the same
        resolved configuration returns it unchanged. ``gate_potential=True`` makes the
        potential term count only on steps where the kNN term is active (SPEC v1.1 §4).
        ``require_score_spread=True`` makes the kNN term active only while the pool's
        scores differ (SPEC v1.3 §3): before the first better episode, a pool of equal
        scores would pay a flat bonus of about ``1.07 * alpha`` per step.

        Returns:
            The task with its resolved configuration.

        Raises:
            TypeError: An unknown keyword, or a value of the wrong type.
            InvalidArgument: A value is out of range or the task id is malformed.
            AlreadyExists: The task exists with a different configuration.
        """
        return self._run(ops.create_task(task_id, config), timeout)

    def get_task(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Task:
        """Return a task with its configuration and live statistics.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.get_task(task_id), timeout)

    def list_tasks(self, *, timeout: Timeout = CLIENT_TIMEOUT) -> list[Task]:
        """Return every task, ordered by task id."""
        return self._run(ops.list_tasks(), timeout)

    def delete_task(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """Delete a task and its pool; its open sessions fail with ``TaskNotFound``.

        Raises:
            TaskNotFound: No such task.
        """
        self._run(ops.delete_task(task_id), timeout)

    def reset_pool(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Task:
        """Empty a task's memory pool (its ``pool_version`` increases); returns the task.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.reset_pool(task_id), timeout)

    def get_pool(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Pool:
        """Return a task's memory pool, trajectories ordered by ``seq``.

        Discrete trajectories come back as ``int64`` arrays ``(L,)``, continuous ones as
        ``float32`` arrays ``(L, action_dim)``.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.get_pool(task_id), timeout)

    def add_trajectory(
        self,
        task_id: str,
        actions: npt.ArrayLike,
        score: float,
        *,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> AddTrajectoryResult:
        """Offer one trajectory (e.g. a demonstration) to a task's pool (SPEC §6 rules).

        Args:
            task_id: The task.
            actions: A 1-D integer array of actions (discrete task) or a 2-D real array
                ``(L, action_dim)`` (continuous task); at least one action.
            score: The episode score S.
            timeout: This call's deadline (see the class).

        Returns:
            Whether it was stored, and the pool version after the call.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: Empty, out-of-range or wrongly-shaped actions, or a
                non-finite score.
        """
        return self._run(ops.add_trajectory(task_id, actions, score), timeout)

    # -- pool files ------------------------------------------------------------------

    def export_pool(
        self, task_id: str, file: PoolFileLike, *, timeout: Timeout = CLIENT_TIMEOUT
    ) -> int:
        """Write a task's config and pool to ``file`` in the pool export format.

        The format (docs/storage.md, "Pool export format") is JSON Lines: a header with
        the task id, its resolved config, the pool version and the trajectory count, then
        one line per stored trajectory in ``seq`` order (``seq``, ``score``, ``actions``);
        :meth:`import_pool`, here or on another server or engine, restores a pool that
        shapes every step as this one does. The server's ``tamrm pool export/import``
        read and write the same files.

        Args:
            task_id: The task.
            file: A path (written whole or not at all: a temporary file beside it, renamed
                over it) or a text file object (written to, left open).
            timeout: Each call's deadline (see the class).

        Returns:
            The number of trajectories written.

        Raises:
            TaskNotFound: No such task.
            OSError: The file cannot be written.
        """
        return _pool_transfer.export_pool(self, task_id, file, timeout)

    def import_pool(
        self,
        file: PoolFileLike,
        task_id: str | None = None,
        *,
        replace: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Task:
        """Restore a pool written by :meth:`export_pool` into a task.

        The whole file is read and checked first: a malformed file raises
        :class:`tamrm.PoolFileError` naming its line, before any call. A task that does
        not exist is created with the file's config. One that exists must have the same
        resolved config and an empty pool; with ``replace=True``, a task of another config
        is deleted and created again (its open sessions fail with ``TaskNotFound``) and a
        non-empty pool of the same config is reset. Then every trajectory is offered with
        ``add_trajectory``, in ``seq`` order: the pool is empty and the file holds at most
        ``pool_capacity`` trajectories, so each is stored, in the same order, with the same
        actions and scores, and the task shapes every step as the exported one did. Its
        ``pool_version`` counts its own changes, not the file's.

        Nothing else may write to the task meanwhile: the import checks that each
        trajectory was stored and the version moved by one each time, and raises
        ``FailedPrecondition`` if not. A call that fails midway leaves the trajectories
        added so far; import again with ``replace=True``.

        Args:
            file: A path, or a text file object (read to its end).
            task_id: The task to import into; ``None``: the file's.
            replace: Replace a task of another config, or the trajectories of a non-empty
                pool, instead of refusing.
            timeout: Each call's deadline (see the class).

        Returns:
            The task after the import.

        Raises:
            PoolFileError: The file is malformed (its message names the line).
            AlreadyExists: The task exists with another config (and not ``replace``).
            FailedPrecondition: The task's pool is not empty (and not ``replace``), or
                the pool changed during the import.
            OSError: The file cannot be read.
        """
        return _pool_transfer.import_pool(self, file, task_id, replace, timeout)

    # -- sessions --------------------------------------------------------------------

    def session(self, task_id: str, num_envs: int = 1, *, local: bool = False) -> Session:
        """Open a session for ``num_envs`` environments of a task.

        The stream opens immediately (the answer to ``Open`` is in ``session.task``). Use
        the session as a context manager so that it is closed.

        With ``local=True`` (a :class:`Client` only; SPEC §13) the session shapes every
        step in this process, against a copy of the task's pool that follows the server
        (a ``Follow`` stream): only episode ends (and a count of steps) cross the
        network. Its methods, arguments, results and errors are a remote session's, and
        one learner alone gets the same values bit for bit; other learners' pool changes
        reach it within the server's staleness bound. A broken stream is re-opened as a
        remote session's is (``resume_timeout_secs``), re-sending the episode ends the
        server had not acknowledged.

        Raises:
            TypeError: ``local=True`` on a :class:`tamrm.Engine` (its sessions are
                in-process already).
            TaskNotFound: No such task.
            InvalidArgument: ``num_envs`` was rejected.
        """
        return Session(self, task_id, num_envs, local=local)
