"""The synchronous client."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, TypeVar

import grpc

from tamrm._batch import prepare_trajectory
from tamrm._errors import Unavailable, from_rpc_error
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._proto.tamrm.v1 import shaping_pb2_grpc as pb_grpc
from tamrm._session import Session
from tamrm._types import AddTrajectoryResult, Pool, Task, Trajectory, config_to_pb

__all__ = ["DEFAULT_TIMEOUT", "Client", "make_channel_options"]

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


def _pool_from_pb(msg: pb.Pool, action_dim: int) -> Pool:
    return Pool(
        task_id=msg.task_id,
        pool_version=int(msg.pool_version),
        trajectories=[Trajectory._from_pb(t, action_dim) for t in msg.trajectories],
    )


class Client:
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
        opts = make_channel_options(options)
        if credentials is None:
            self._channel = grpc.insecure_channel(target, options=opts)
        else:
            self._channel = grpc.secure_channel(target, credentials, options=opts)
        self._stub = pb_grpc.ShapingStub(self._channel)
        self._metadata = tuple(metadata) if metadata else None

    def _call(self, method: Callable[..., _T], request: Any) -> _T:
        try:
            return method(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as exc:
            raise from_rpc_error(exc) from None

    # -- tasks -----------------------------------------------------------------------

    def create_task(
        self,
        task_id: str,
        *,
        num_actions: int | None = None,
        action_dim: int | None = None,
        pool_capacity: int | None = None,
        k: int | None = None,
        start_step: int | None = None,
        min_pool_size: int | None = None,
        alpha: float | None = None,
        beta: float | None = None,
        gamma: float | None = None,
        max_trajectory_len: int | None = None,
        gate_potential: bool | None = None,
    ) -> Task:
        """Create a task; arguments left ``None`` take the server's defaults (SPEC §1.1).

        Exactly one of ``num_actions`` (discrete actions ``0..n-1``) and ``action_dim``
        (continuous action vectors) must be given. Creating an existing task with the same
        resolved configuration returns it unchanged. ``gate_potential=True`` makes the
        potential term count only on steps where the kNN term is active (SPEC v1.1 §4).

        Returns:
            The task with its resolved configuration.

        Raises:
            InvalidArgument: A value is out of range or the task id is malformed.
            AlreadyExists: The task exists with a different configuration.
        """
        config = config_to_pb(
            {
                "num_actions": num_actions,
                "action_dim": action_dim,
                "pool_capacity": pool_capacity,
                "k": k,
                "start_step": start_step,
                "min_pool_size": min_pool_size,
                "alpha": alpha,
                "beta": beta,
                "gamma": gamma,
                "max_trajectory_len": max_trajectory_len,
                "gate_potential": gate_potential,
            }
        )
        msg = self._call(
            self._stub.CreateTask, pb.CreateTaskRequest(task_id=task_id, config=config)
        )
        return Task._from_pb(msg)

    def get_task(self, task_id: str) -> Task:
        """Return a task with its configuration and live statistics.

        Raises:
            TaskNotFound: No such task.
        """
        return Task._from_pb(self._call(self._stub.GetTask, pb.GetTaskRequest(task_id=task_id)))

    def list_tasks(self) -> list[Task]:
        """Return every task, ordered by task id."""
        msg = self._call(self._stub.ListTasks, pb.ListTasksRequest())
        return [Task._from_pb(t) for t in msg.tasks]

    def delete_task(self, task_id: str) -> None:
        """Delete a task and its pool; its open sessions fail with ``TaskNotFound``.

        Raises:
            TaskNotFound: No such task.
        """
        self._call(self._stub.DeleteTask, pb.DeleteTaskRequest(task_id=task_id))

    def reset_pool(self, task_id: str) -> Task:
        """Empty a task's memory pool (its ``pool_version`` increases); returns the task.

        Raises:
            TaskNotFound: No such task.
        """
        msg = self._call(self._stub.ResetPool, pb.ResetPoolRequest(task_id=task_id))
        return Task._from_pb(msg)

    def get_pool(self, task_id: str) -> Pool:
        """Return a task's memory pool, trajectories ordered by ``seq``.

        Discrete trajectories come back as ``int64`` arrays ``(L,)``, continuous ones as
        ``float32`` arrays ``(L, action_dim)``.

        Raises:
            TaskNotFound: No such task.
        """
        msg = self._call(self._stub.GetPool, pb.GetPoolRequest(task_id=task_id))
        action_dim = 0
        if any(len(t.action_vectors) for t in msg.trajectories):
            action_dim = self.get_task(task_id).config.action_dim
        return _pool_from_pb(msg, action_dim)

    def add_trajectory(self, task_id: str, actions: Any, score: float) -> AddTrajectoryResult:
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
        request = pb.AddTrajectoryRequest(
            task_id=task_id, trajectory=prepare_trajectory(actions, score)
        )
        msg = self._call(self._stub.AddTrajectory, request)
        return AddTrajectoryResult(inserted=bool(msg.inserted), pool_version=int(msg.pool_version))

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

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<tamrm.Client target={self.target!r}>"
