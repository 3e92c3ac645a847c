"""The synchronous client."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import grpc
import numpy.typing as npt

from tamrm import _ops as ops
from tamrm._closing import Closing
from tamrm._errors import Unavailable, from_rpc_error
from tamrm._proto.tamrm.v1 import shaping_pb2_grpc as pb_grpc
from tamrm._session import Session
from tamrm._types import AddTrajectoryResult, Pool, Task, TaskOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["DEFAULT_TIMEOUT", "Client", "ClientCore", "make_channel_options"]

#: Default deadline, in seconds, of every unary call (not of ``Shape`` streams).
DEFAULT_TIMEOUT = 30.0

_T = TypeVar("_T")


def make_channel_options(
    options: Sequence[tuple[str, Any]] | None,
) -> list[tuple[str, Any]]:
    """Return the clients' channel options: large messages allowed, plus ``options``."""
    base: dict[str, Any] = {
        "grpc.max_send_message_length": 64 * 1024 * 1024,
        "grpc.max_receive_message_length": 256 * 1024 * 1024,
    }
    for key, value in options or ():
        base[key] = value
    return list(base.items())


class ClientCore:
    """What the sync and asyncio clients share: the channel's settings, stub and metadata."""

    def __init__(
        self,
        target: str,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        credentials: grpc.ChannelCredentials | None = None,
        options: Sequence[tuple[str, Any]] | None = None,
        metadata: Sequence[tuple[str, str]] | None = None,
    ) -> None:
        self.target = target
        self.timeout = timeout
        self._channel = self._make_channel(target, credentials, make_channel_options(options))
        self._stub = pb_grpc.ShapingStub(self._channel)
        self._metadata = tuple(metadata) if metadata else None

    def _make_channel(
        self,
        target: str,
        credentials: grpc.ChannelCredentials | None,
        options: list[tuple[str, Any]],
    ) -> Any:
        raise NotImplementedError


class Client(ClientCore, Closing):
    """A connection to a tamrm server.

    Every method takes and returns plain Python / numpy values and raises a
    :class:`tamrm.TamrmError` subclass (:class:`tamrm.TaskNotFound`,
    :class:`tamrm.InvalidArgument`, ...) carrying the server's message on failure.

    Example::

        with tamrm.Client("127.0.0.1:50051") as client:
            client.create_task("cartpole", num_actions=2)
            with client.session("cartpole", num_envs=8) as session:
                shaped = session.step(actions, rewards, terminated, truncated)

    Args:
        target: The server address, ``host:port`` (any gRPC target string).
        timeout: Deadline in seconds of each unary call (``None``: no deadline).
        credentials: Channel credentials for TLS; ``None`` for a plaintext channel.
        options: Extra gRPC channel options.
        metadata: Metadata (e.g. an authorization header) sent with every call.
    """

    def _make_channel(
        self,
        target: str,
        credentials: grpc.ChannelCredentials | None,
        options: list[tuple[str, Any]],
    ) -> grpc.Channel:
        if credentials is None:
            return grpc.insecure_channel(target, options=options)
        return grpc.secure_channel(target, credentials, options=options)

    def _call(self, rpc: ops.Rpc) -> Any:
        method = getattr(self._stub, rpc.method)
        try:
            return method(rpc.request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as exc:
            raise from_rpc_error(exc) from None

    def _run(self, op: ops.Op[_T]) -> _T:
        return ops.run(op, self._call)

    # -- tasks -----------------------------------------------------------------------

    def create_task(self, task_id: str, **config: Unpack[TaskOptions]) -> Task:
        """Create a task; keywords left out (or ``None``) take the server's defaults.

        The keywords are exactly the ``TaskConfig`` fields (:data:`tamrm.CONFIG_FIELDS`,
        typed by :class:`tamrm.TaskOptions`; SPEC §1.1): ``num_actions``, ``action_dim``,
        ``pool_capacity``, ``k``, ``start_step``, ``min_pool_size``, ``alpha``, ``beta``,
        ``gamma``, ``max_trajectory_len``, ``gate_potential``.

        Exactly one of ``num_actions`` (discrete actions ``0..n-1``) and ``action_dim``
        (continuous action vectors) must be given. Creating an existing task with the same
        resolved configuration returns it unchanged. ``gate_potential=True`` makes the
        potential term count only on steps where the kNN term is active (SPEC v1.1 §4).

        Returns:
            The task with its resolved configuration.

        Raises:
            TypeError: An unknown keyword, or a value of the wrong type.
            InvalidArgument: A value is out of range or the task id is malformed.
            AlreadyExists: The task exists with a different configuration.
        """
        return self._run(ops.create_task(task_id, config))

    def get_task(self, task_id: str) -> Task:
        """Return a task with its configuration and live statistics.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.get_task(task_id))

    def list_tasks(self) -> list[Task]:
        """Return every task, ordered by task id."""
        return self._run(ops.list_tasks())

    def delete_task(self, task_id: str) -> None:
        """Delete a task and its pool; its open sessions fail with ``TaskNotFound``.

        Raises:
            TaskNotFound: No such task.
        """
        self._run(ops.delete_task(task_id))

    def reset_pool(self, task_id: str) -> Task:
        """Empty a task's memory pool (its ``pool_version`` increases); returns the task.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.reset_pool(task_id))

    def get_pool(self, task_id: str) -> Pool:
        """Return a task's memory pool, trajectories ordered by ``seq``.

        Discrete trajectories come back as ``int64`` arrays ``(L,)``, continuous ones as
        ``float32`` arrays ``(L, action_dim)``.

        Raises:
            TaskNotFound: No such task.
        """
        return self._run(ops.get_pool(task_id))

    def add_trajectory(
        self, task_id: str, actions: npt.ArrayLike, score: float
    ) -> AddTrajectoryResult:
        """Offer one trajectory (e.g. a demonstration) to a task's pool (SPEC §6 rules).

        Args:
            task_id: The task.
            actions: A 1-D integer array of actions (discrete task) or a 2-D real array
                ``(L, action_dim)`` (continuous task); at least one action.
            score: The episode score S.

        Returns:
            Whether it was stored, and the pool version after the call.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: Empty, out-of-range or wrongly-shaped actions, or a
                non-finite score.
        """
        return self._run(ops.add_trajectory(task_id, actions, score))

    # -- sessions --------------------------------------------------------------------

    def session(self, task_id: str, num_envs: int = 1) -> Session:
        """Open a ``Shape`` stream for ``num_envs`` environments of a task.

        The stream opens immediately (the server's answer is in ``session.task``). Use
        the session as a context manager so that it is closed.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: ``num_envs`` was rejected.
        """
        return Session(self._stub, task_id, num_envs, metadata=self._metadata)

    # -- lifecycle -------------------------------------------------------------------

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until the channel is connected.

        Raises:
            Unavailable: Not connected within ``timeout`` seconds.
        """
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            raise Unavailable(f"could not connect to {self.target} in {timeout}s") from None

    def close(self) -> None:
        """Close the channel (open sessions are cancelled)."""
        self._channel.close()

    def __repr__(self) -> str:
        return f"<tamrm.Client target={self.target!r}>"
