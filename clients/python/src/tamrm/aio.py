"""The asyncio twin of :class:`tamrm.Client`, for async training loops.

Same methods, same arguments, same return values and exceptions as the synchronous client,
but every call is a coroutine::

    import tamrm.aio

    async with tamrm.aio.Client("127.0.0.1:50051") as client:
        await client.create_task("cartpole", num_actions=2)
        async with client.session("cartpole", num_envs=8) as session:
            shaped = await session.step(actions, rewards, terminated, truncated)

Requests and answers are built and decoded by the same code as the synchronous client's
(``tamrm._ops`` for the unary calls, :class:`tamrm._stream.SessionCore` for the stream);
this module only awaits them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Awaitable, Generator
from typing import TYPE_CHECKING, Any, TypeVar

import grpc
import grpc.aio
import numpy.typing as npt

from tamrm import _ops as ops
from tamrm._batch import StepInput
from tamrm._client import ClientCore
from tamrm._closing import AsyncClosing
from tamrm._errors import TamrmError, from_rpc_error, from_status
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._stream import SessionCore
from tamrm._types import AddTrajectoryResult, Pool, StepResult, Task, TaskOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["AsyncSession", "Client"]

_T = TypeVar("_T")


class AsyncSession(SessionCore[Awaitable[StepResult]], AsyncClosing):
    """One ``Shape`` stream, asyncio flavour; see :class:`tamrm.Session`.

    Returned (not yet open) by :meth:`Client.session`: open it with ``async with`` (or
    ``await session.open()`` / ``await client.session(...)``), then ``await`` each
    :meth:`step`. Not safe for concurrent steps on the same session: await one step
    before sending the next.
    """

    def _start(self) -> None:
        # The stream opens on ``open()`` / ``async with``.
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
        await self._write(self._open_request())
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
        self._failed(err)
        if self._call is not None:
            self._call.cancel()

    async def _exchange(self, step: StepInput) -> StepResult:
        prepared = self._prepare(step)
        if isinstance(prepared, StepResult):
            return prepared
        try:
            await self._write(prepared.request)
            resp = await self._read()
        except TamrmError as err:
            if self._rejected(err):
                # The batch changed nothing: go on on a new stream with every episode resumed.
                with contextlib.suppress(TamrmError):
                    await self.open()
            raise
        try:
            return self._shaped(resp, prepared)
        except TamrmError as err:
            self._abort(err)
            raise

    async def restart(self) -> None:
        """Close the stream and open a new one; episodes in progress are discarded."""
        await self.close()
        await self.open()

    async def close(self) -> None:
        """Half-close the stream and wait for the server to end it. Idempotent."""
        if not self._closing():
            return
        call = self._call
        try:
            await call.done_writing()
            while await call.read() is not grpc.aio.EOF:
                pass
        except grpc.RpcError:
            pass

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def __aenter__(self) -> AsyncSession:
        return await self.open()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<tamrm.aio.AsyncSession task_id={self.task_id!r} num_envs={self.num_envs} {state}>"


class Client(ClientCore, AsyncClosing):
    """Asyncio client of a tamrm server; see :class:`tamrm.Client` for every method.

    Create it inside a running event loop.

    Args:
        target: The server address, ``host:port`` (default: ``$TAMRM_ADDRESS``, else
            ``127.0.0.1:50051``); see :class:`tamrm.Client`.
        timeout: Deadline in seconds of each unary call (``None``: no deadline).
        credentials: Channel credentials for TLS; ``None`` for plaintext.
        options: Extra gRPC channel options.
        metadata: Metadata sent with every call.
    """

    def _make_channel(
        self,
        target: str,
        credentials: grpc.ChannelCredentials | None,
        options: list[tuple[str, Any]],
    ) -> grpc.aio.Channel:
        if credentials is None:
            return grpc.aio.insecure_channel(target, options=options)
        return grpc.aio.secure_channel(target, credentials, options=options)

    async def _call(self, rpc: ops.Rpc) -> Any:
        method = getattr(self._stub, rpc.method)
        try:
            return await method(rpc.request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as exc:
            raise from_rpc_error(exc) from None

    async def _run(self, op: ops.Op[_T]) -> _T:
        return await ops.run_async(op, self._call)

    async def create_task(self, task_id: str, **config: Unpack[TaskOptions]) -> Task:
        """Create a task; see :meth:`tamrm.Client.create_task`."""
        return await self._run(ops.create_task(task_id, config))

    async def get_task(self, task_id: str) -> Task:
        """Return a task; see :meth:`tamrm.Client.get_task`."""
        return await self._run(ops.get_task(task_id))

    async def list_tasks(self) -> list[Task]:
        """Return every task, ordered by task id."""
        return await self._run(ops.list_tasks())

    async def delete_task(self, task_id: str) -> None:
        """Delete a task and its pool; see :meth:`tamrm.Client.delete_task`."""
        await self._run(ops.delete_task(task_id))

    async def reset_pool(self, task_id: str) -> Task:
        """Empty a task's memory pool; see :meth:`tamrm.Client.reset_pool`."""
        return await self._run(ops.reset_pool(task_id))

    async def get_pool(self, task_id: str) -> Pool:
        """Return a task's memory pool; see :meth:`tamrm.Client.get_pool`."""
        return await self._run(ops.get_pool(task_id))

    async def add_trajectory(
        self, task_id: str, actions: npt.ArrayLike, score: float
    ) -> AddTrajectoryResult:
        """Offer a trajectory to a task's pool; see :meth:`tamrm.Client.add_trajectory`."""
        return await self._run(ops.add_trajectory(task_id, actions, score))

    def session(self, task_id: str, num_envs: int = 1) -> AsyncSession:
        """Return an (unopened) :class:`AsyncSession`; open it with ``async with`` or ``await``."""
        return AsyncSession(self, task_id, num_envs)

    async def close(self) -> None:
        """Close the channel (open sessions are cancelled)."""
        await self._channel.close()

    def __repr__(self) -> str:
        return f"<tamrm.aio.Client target={self.target!r}>"
