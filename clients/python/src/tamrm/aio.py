"""The asyncio twin of :class:`tamrm.Client`, for async training loops.

Same methods, same arguments, same return values and exceptions as the synchronous client,
but every call is a coroutine::

    import tamrm.aio

    async with tamrm.aio.Client("127.0.0.1:50051") as client:
        await client.create_task("cartpole", num_actions=2)
        async with client.session("cartpole", num_envs=8) as session:
            shaped = await session.step(actions, rewards, terminated, truncated)
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Generator, Sequence
from types import TracebackType
from typing import Any, TypeVar

import grpc
import grpc.aio

from tamrm._batch import prepare_batch, prepare_trajectory
from tamrm._client import DEFAULT_TIMEOUT, _pool_from_pb, make_channel_options
from tamrm._errors import TamrmError, from_rpc_error, from_status
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._proto.tamrm.v1 import shaping_pb2_grpc as pb_grpc
from tamrm._session import _SessionBase
from tamrm._types import AddTrajectoryResult, Pool, StepResult, Task, config_to_pb

__all__ = ["AsyncSession", "Client"]

_T = TypeVar("_T")


class AsyncSession(_SessionBase):
    """One ``Shape`` stream, asyncio flavour; see :class:`tamrm.Session`.

    Returned (not yet open) by :meth:`Client.session`: open it with ``async with`` (or
    ``await session.open()`` / ``await client.session(...)``), then ``await`` each
    :meth:`step`. Not safe for concurrent steps on the same session: await one step
    before sending the next.
    """

    def __init__(
        self,
        stub: pb_grpc.ShapingStub,
        task_id: str,
        num_envs: int,
        *,
        metadata: Sequence[tuple[str, str]] | None = None,
    ) -> None:
        """Prepare the session; the stream opens on ``open()`` / ``async with``."""
        self._init_state(task_id, num_envs)
        self._stub = stub
        self._metadata = tuple(metadata) if metadata else None
        self._call: Any = None

    async def open(self) -> AsyncSession:
        """Open the stream and wait for the server's answer to ``Open``.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: ``num_envs`` was rejected.
        """
        if not self._closed:
            return self
        self._call = self._stub.Shape(metadata=self._metadata)
        await self._write(
            pb.ShapeRequest(open=pb.Open(task_id=self.task_id, num_envs=self.num_envs))
        )
        self._opened(await self._read())
        return self

    async def _write(self, request: pb.ShapeRequest) -> None:
        try:
            await self._call.write(request)
        except grpc.RpcError as exc:
            err = from_rpc_error(exc)
            self._abort(err)
            raise err from None
        except Exception:
            # A write after the call ended (e.g. the server already failed it): the
            # status says why.
            err = await self._status_error()
            self._abort(err)
            raise err from None

    async def _status_error(self) -> TamrmError:
        try:
            code = await self._call.code()
            details = await self._call.details()
        except Exception:  # pragma: no cover - defensive
            return TamrmError("the Shape stream failed")
        return from_status(code, details)

    async def _read(self) -> pb.ShapeResponse:
        try:
            resp = await self._call.read()
        except grpc.RpcError as exc:
            err = from_rpc_error(exc)
            self._abort(err)
            raise err from None
        if resp is grpc.aio.EOF:
            code = await self._call.code()
            if code == grpc.StatusCode.OK:
                err = TamrmError("the server ended the Shape stream unexpectedly")
            else:
                err = await self._status_error()
            self._abort(err)
            raise err
        msg: pb.ShapeResponse = resp
        return msg

    def _abort(self, err: BaseException) -> None:
        self._closed = True
        self._error = err
        if self._call is not None:
            self._call.cancel()

    async def step(
        self,
        actions: Any,
        rewards: Any,
        terminated: Any = None,
        truncated: Any = None,
        *,
        values: Any = None,
        next_values: Any = None,
        q_values: Any = None,
        next_q_values: Any = None,
        episode_scores: Any = None,
        env_ids: Any = None,
    ) -> StepResult:
        """Shape one vector step; see :meth:`tamrm.Session.step` for the arguments."""
        self._check_open()
        prepared = prepare_batch(
            self.task.config,
            self.num_envs,
            actions,
            rewards,
            terminated,
            truncated,
            values=values,
            next_values=next_values,
            q_values=q_values,
            next_q_values=next_q_values,
            episode_scores=episode_scores,
            env_ids=env_ids,
        )
        if prepared.size == 0:
            return StepResult._empty(self._pool_version)
        await self._write(prepared.request)
        resp = await self._read()
        try:
            return self._shaped(resp, prepared.env_ids, prepared.done)
        except TamrmError as err:
            self._abort(err)
            raise

    async def restart(self) -> None:
        """Close the stream and open a new one; episodes in progress are discarded."""
        await self.close()
        await self.open()

    async def close(self) -> None:
        """Half-close the stream and wait for the server to end it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        call = self._call
        try:
            await call.done_writing()
            while await call.read() is not grpc.aio.EOF:
                pass
        except grpc.RpcError:
            pass
        self._episode_steps[:] = 0

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def __aenter__(self) -> AsyncSession:
        return await self.open()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<tamrm.aio.AsyncSession task_id={self.task_id!r} num_envs={self.num_envs} {state}>"


class Client:
    """Asyncio client of a tamrm server; see :class:`tamrm.Client` for every method.

    Create it inside a running event loop.

    Args:
        target: The server address, ``host:port``.
        timeout: Deadline in seconds of each unary call (``None``: no deadline).
        credentials: Channel credentials for TLS; ``None`` for plaintext.
        options: Extra gRPC channel options.
        metadata: Metadata sent with every call.
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
            self._channel = grpc.aio.insecure_channel(target, options=opts)
        else:
            self._channel = grpc.aio.secure_channel(target, credentials, options=opts)
        self._stub = pb_grpc.ShapingStub(self._channel)
        self._metadata = tuple(metadata) if metadata else None

    async def _call(self, method: Callable[..., Awaitable[_T]], request: Any) -> _T:
        try:
            return await method(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as exc:
            raise from_rpc_error(exc) from None

    async def create_task(
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
        """Create a task; see :meth:`tamrm.Client.create_task`."""
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
        msg = await self._call(
            self._stub.CreateTask, pb.CreateTaskRequest(task_id=task_id, config=config)
        )
        return Task._from_pb(msg)

    async def get_task(self, task_id: str) -> Task:
        """Return a task; see :meth:`tamrm.Client.get_task`."""
        msg = await self._call(self._stub.GetTask, pb.GetTaskRequest(task_id=task_id))
        return Task._from_pb(msg)

    async def list_tasks(self) -> list[Task]:
        """Return every task, ordered by task id."""
        msg = await self._call(self._stub.ListTasks, pb.ListTasksRequest())
        return [Task._from_pb(t) for t in msg.tasks]

    async def delete_task(self, task_id: str) -> None:
        """Delete a task and its pool; see :meth:`tamrm.Client.delete_task`."""
        await self._call(self._stub.DeleteTask, pb.DeleteTaskRequest(task_id=task_id))

    async def reset_pool(self, task_id: str) -> Task:
        """Empty a task's memory pool; see :meth:`tamrm.Client.reset_pool`."""
        msg = await self._call(self._stub.ResetPool, pb.ResetPoolRequest(task_id=task_id))
        return Task._from_pb(msg)

    async def get_pool(self, task_id: str) -> Pool:
        """Return a task's memory pool; see :meth:`tamrm.Client.get_pool`."""
        msg = await self._call(self._stub.GetPool, pb.GetPoolRequest(task_id=task_id))
        action_dim = 0
        if any(len(t.action_vectors) for t in msg.trajectories):
            action_dim = (await self.get_task(task_id)).config.action_dim
        return _pool_from_pb(msg, action_dim)

    async def add_trajectory(self, task_id: str, actions: Any, score: float) -> AddTrajectoryResult:
        """Offer a trajectory to a task's pool; see :meth:`tamrm.Client.add_trajectory`."""
        request = pb.AddTrajectoryRequest(
            task_id=task_id, trajectory=prepare_trajectory(actions, score)
        )
        msg = await self._call(self._stub.AddTrajectory, request)
        return AddTrajectoryResult(inserted=bool(msg.inserted), pool_version=int(msg.pool_version))

    def session(self, task_id: str, num_envs: int = 1) -> AsyncSession:
        """Return an (unopened) :class:`AsyncSession`; open it with ``async with`` or ``await``."""
        return AsyncSession(self._stub, task_id, num_envs, metadata=self._metadata)

    async def close(self) -> None:
        """Close the channel (open sessions are cancelled)."""
        await self._channel.close()

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"<tamrm.aio.Client target={self.target!r}>"
