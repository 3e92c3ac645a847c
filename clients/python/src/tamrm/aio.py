"""The asyncio twin of :class:`tamrm.Client`, for async training loops.

Same methods, same arguments, same return values and exceptions as the synchronous client,
but every call is a coroutine::

    import tamrm.aio

    async with tamrm.aio.Client("127.0.0.1:50051") as client:
        await client.create_task("cartpole", num_actions=2)
        async with client.session("cartpole", num_envs=8) as session:
            shaped = await session.step(actions, rewards, terminated, truncated)

Each coroutine awaits the synchronous client's native call (``tamrm._native``, which
releases the GIL for its round trip) on a worker thread, so the event loop goes on while
the answer travels: requests, answers, checks and errors are exactly the synchronous
client's.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable, Generator, Mapping
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt

from tamrm._address import Targets
from tamrm._calls import CLIENT_TIMEOUT, DEFAULT_TIMEOUT, Timeout
from tamrm._client import Client as _SyncClient
from tamrm._closing import AsyncClosing
from tamrm._connection import ConnectionOptions
from tamrm._errors import SessionClosed
from tamrm._pool_file import PoolFileLike
from tamrm._session import Session
from tamrm._types import AddTrajectoryResult, Pool, StepResult, Task, TaskConfig, TaskOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["AsyncSession", "Client"]

_T = TypeVar("_T")


async def _in_thread(fn: Callable[..., _T], /, *args: Any, **kwargs: Any) -> _T:
    """Await ``fn(*args, **kwargs)`` run on the loop's default executor."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(None, functools.partial(fn, *args, **kwargs))


class AsyncSession(AsyncClosing):
    """One shaping stream, asyncio flavour; see :class:`tamrm.Session`.

    Returned (not yet open) by :meth:`Client.session`: open it with ``async with`` (or
    ``await session.open()`` / ``await client.session(...)``), then ``await`` each
    :meth:`step`. Not safe for concurrent steps on the same session: await one step
    before sending the next.

    Attributes:
        local: Whether it is a local session (``client.session(..., local=True)``).
    """

    def __init__(self, client: Client, task_id: str, num_envs: int, *, local: bool = False) -> None:
        if not isinstance(local, bool):
            raise TypeError(f"local must be a bool, got {type(local).__name__}")
        if not isinstance(task_id, str):
            raise TypeError(f"task_id must be a str, got {type(task_id).__name__}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {type(num_envs).__name__}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.task_id = task_id
        self.num_envs = int(num_envs)
        self.local = local
        self._client = client
        self._session: Session | None = None

    async def open(self) -> AsyncSession:
        """Open the stream and wait for the answer to ``Open``.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: ``num_envs`` was rejected.
        """
        if self._session is None or self._session.closed:
            self._session = await _in_thread(
                Session, self._client._sync, self.task_id, self.num_envs, local=self.local
            )
        return self

    def _open_session(self) -> Session:
        if self._session is None:
            raise SessionClosed(f"the session on task {self.task_id!r} is not open")
        return self._session

    @property
    def task(self) -> Task:
        """The task as it was when the stream opened."""
        return self._open_session().task

    @property
    def config(self) -> TaskConfig:
        """The task's resolved configuration, as returned when the stream opened."""
        return self._open_session().config

    @property
    def closed(self) -> bool:
        """Whether the stream is closed (or not opened yet)."""
        return self._session is None or self._session.closed

    @property
    def pool_version(self) -> int:
        """The task's pool version after the last answered batch (or at open)."""
        return self._open_session().pool_version

    @property
    def episode_steps(self) -> npt.NDArray[np.int64]:
        """Per environment, the steps sent so far in its current (unfinished) episode."""
        if self._session is None:
            return np.zeros(self.num_envs, dtype=np.int64)
        return self._session.episode_steps

    @property
    def episodes_in_progress(self) -> npt.NDArray[np.bool_]:
        """Per environment, whether an episode has been started and not yet ended."""
        return np.greater(self.episode_steps, 0)

    async def step(
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
        """Shape one vector step; arguments, result and errors as :meth:`tamrm.Session.step`."""
        session = self._open_session()
        return await _in_thread(
            session.step,
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

    def abandon(self, env_ids: npt.ArrayLike) -> None:
        """Drop the current episodes of ``env_ids``; see :meth:`tamrm.Session.abandon`.

        A plain method: nothing is sent until the next step.
        """
        self._open_session().abandon(env_ids)

    async def restart(self) -> None:
        """Close the stream and open a new one on the task; see :meth:`tamrm.Session.restart`."""
        await _in_thread(self._open_session().restart)

    async def close(self) -> None:
        """End the stream (idempotent); episodes still in progress are discarded."""
        if self._session is not None:
            await _in_thread(self._session.close)

    def __await__(self) -> Generator[Any, None, AsyncSession]:
        return self.open().__await__()

    async def __aenter__(self) -> AsyncSession:
        return await self.open()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        local = " local" if self.local else ""
        return (
            f"<tamrm.aio.AsyncSession task_id={self.task_id!r} num_envs={self.num_envs}"
            f"{local} {state}>"
        )


class Client(AsyncClosing):
    """Asyncio client of a tamrm server; see :class:`tamrm.Client` for every method.

    Args:
        target: The server address, ``host:port``, or a sequence of replicas' addresses
            (default: ``$TAMRM_ADDRESS``, else ``127.0.0.1:50051``); see
            :class:`tamrm.Client`.
        timeout: Default deadline in seconds of each unary call (``None``: no deadline);
            each method's ``timeout=`` overrides it for one call.
        **connection: How to connect, exactly as :class:`tamrm.Client`: ``metadata``,
            ``tls``, ``root_certificates``, ``certificate_chain``, ``private_key``,
            ``tls_server_name``, ``keepalive_secs``, ``keepalive_timeout_secs``,
            ``api_key``, ``resume_timeout_secs``, ``busy_poll_us``
            (:class:`tamrm.ConnectionOptions`).
    """

    def __init__(
        self,
        target: Targets | None = None,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        **connection: Unpack[ConnectionOptions],
    ) -> None:
        self._sync = _SyncClient(target, timeout=timeout, **connection)
        self.target = self._sync.target
        self.targets = self._sync.targets
        self.timeout = timeout

    @property
    def tls(self) -> bool:
        """Whether the client connects with TLS."""
        return self._sync.tls

    async def create_task(
        self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT, **config: Unpack[TaskOptions]
    ) -> Task:
        """Create a task; see :meth:`tamrm.Client.create_task`."""
        return await _in_thread(self._sync.create_task, task_id, timeout=timeout, **config)

    async def get_task(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Task:
        """Return a task; see :meth:`tamrm.Client.get_task`."""
        return await _in_thread(self._sync.get_task, task_id, timeout=timeout)

    async def list_tasks(self, *, timeout: Timeout = CLIENT_TIMEOUT) -> list[Task]:
        """Return every task, ordered by task id."""
        return await _in_thread(self._sync.list_tasks, timeout=timeout)

    async def delete_task(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """Delete a task and its pool; see :meth:`tamrm.Client.delete_task`."""
        await _in_thread(self._sync.delete_task, task_id, timeout=timeout)

    async def reset_pool(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Task:
        """Empty a task's memory pool; see :meth:`tamrm.Client.reset_pool`."""
        return await _in_thread(self._sync.reset_pool, task_id, timeout=timeout)

    async def get_pool(self, task_id: str, *, timeout: Timeout = CLIENT_TIMEOUT) -> Pool:
        """Return a task's memory pool; see :meth:`tamrm.Client.get_pool`."""
        return await _in_thread(self._sync.get_pool, task_id, timeout=timeout)

    async def add_trajectory(
        self,
        task_id: str,
        actions: npt.ArrayLike,
        score: float,
        *,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> AddTrajectoryResult:
        """Offer a trajectory to a task's pool; see :meth:`tamrm.Client.add_trajectory`."""
        return await _in_thread(self._sync.add_trajectory, task_id, actions, score, timeout=timeout)

    async def export_pool(
        self, task_id: str, file: PoolFileLike, *, timeout: Timeout = CLIENT_TIMEOUT
    ) -> int:
        """Write a task's pool to a file; see :meth:`tamrm.Client.export_pool`."""
        return await _in_thread(self._sync.export_pool, task_id, file, timeout=timeout)

    async def import_pool(
        self,
        file: PoolFileLike,
        task_id: str | None = None,
        *,
        replace: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Task:
        """Restore a pool from a file; see :meth:`tamrm.Client.import_pool`."""
        return await _in_thread(
            self._sync.import_pool, file, task_id, replace=replace, timeout=timeout
        )

    def session(self, task_id: str, num_envs: int = 1, *, local: bool = False) -> AsyncSession:
        """Return an (unopened) :class:`AsyncSession`; open it with ``async with`` or ``await``.

        ``local=True``: a local session (shaped in-process against a followed copy of
        the task's pool); see :meth:`tamrm.Client.session`.
        """
        return AsyncSession(self, task_id, num_envs, local=local)

    async def wait_ready(self, timeout: float = 10.0) -> None:
        """Wait until the server can be reached; see :meth:`tamrm.Client.wait_ready`."""
        await _in_thread(self._sync.wait_ready, timeout)

    async def close(self) -> None:
        """Close the client."""
        self._sync.close()

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (self.targets, self.timeout, self._sync._connection))

    def __repr__(self) -> str:
        tls = " tls" if self.tls else ""
        where = f"target={self.target!r}" if len(self.targets) == 1 else f"targets={self.targets!r}"
        return f"<tamrm.aio.Client {where}{tls}>"


def _rebuild(target: Targets, timeout: float | None, connection: ConnectionOptions) -> Client:
    return Client(target, timeout=timeout, **connection)
