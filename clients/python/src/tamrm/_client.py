"""The synchronous client."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import numpy.typing as npt
from google.protobuf import message_factory
from google.protobuf.message import Message

from tamrm import _native
from tamrm import _ops as ops
from tamrm._closing import Closing
from tamrm._errors import from_native
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._session import Session
from tamrm._types import AddTrajectoryResult, Pool, Task, TaskOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "ADDRESS_ENV",
    "DEFAULT_ADDRESS",
    "DEFAULT_TIMEOUT",
    "Client",
    "TaskCalls",
    "parse_target",
]

#: Default deadline, in seconds, of every unary call (not of ``Shape`` streams).
DEFAULT_TIMEOUT = 30.0

#: The environment variable holding the clients' default address.
ADDRESS_ENV = "TAMRM_ADDRESS"

#: The address used when neither a target nor ``TAMRM_ADDRESS`` is given.
DEFAULT_ADDRESS = "127.0.0.1:50051"

# gRPC's own name-resolver schemes, passed through unchanged (``unix:/tmp/tamrm.sock``).
_GRPC_SCHEMES = ("dns:", "unix:", "unix-abstract:", "ipv4:", "ipv6:", "vsock:")
_HOST_PORT = re.compile(
    r"(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?):(?P<port>[0-9]+)"
)


def parse_target(target: str | None) -> str:
    """Return the gRPC target for ``target``, checked; ``None``: ``$TAMRM_ADDRESS`` or the default.

    Surrounding whitespace is dropped (an address read from ``--port-file`` ends in a
    newline). Accepted: ``host:port`` (a host name, an IPv4 address or a bracketed IPv6
    address; port 1-65535), or a target with one of gRPC's own schemes (``dns:``,
    ``unix:``, ``ipv4:``, ...).

    Raises:
        TypeError: ``target`` is not a string.
        ValueError: A URL (``http://host:port``), a missing port or another malformed
            address; the message says what is expected.
    """
    source = "target"
    if target is None:
        target = os.environ.get(ADDRESS_ENV)
        if target is None or not target.strip():
            return DEFAULT_ADDRESS
        source = f"${ADDRESS_ENV}"
    if not isinstance(target, str):
        raise TypeError(f"target must be a str 'host:port', got {type(target).__name__}")
    stripped = target.strip()
    expected = f"expected host:port, e.g. {DEFAULT_ADDRESS} (the server's --listen address)"
    if stripped.startswith(_GRPC_SCHEMES):
        return stripped
    if "://" in stripped:
        rest = stripped.split("://", 1)[1].rstrip("/")
        raise ValueError(
            f"{source} {target!r} is a URL: {expected}; use {rest!r} without the scheme"
        )
    match = _HOST_PORT.fullmatch(stripped)
    if match is None:
        if ":" not in stripped and stripped:
            raise ValueError(f"{source} {target!r} has no port: {expected}")
        raise ValueError(f"{source} {target!r} is not an address: {expected}")
    port = int(match.group("port"))
    if not 1 <= port <= 65535:
        raise ValueError(f"{source} {target!r}: port {port} is not in 1..65535; {expected}")
    return stripped


_T = TypeVar("_T")


def _rebuild_client(
    target: str,
    timeout: float | None,
    metadata: Sequence[tuple[str, str]] | None,
    api_key: str | None = None,
) -> Client:
    return Client(target, timeout=timeout, metadata=metadata, api_key=api_key)


def resolve_api_key(api_key: str | None) -> str | None:
    """The API key to send: ``api_key``, else ``$TAMRM_API_KEY``, else none.

    Raises:
        ValueError: The key is empty or cannot travel in a header (blanks, control
            characters or non-ASCII).
    """
    key = api_key if api_key is not None else os.environ.get("TAMRM_API_KEY") or None
    if key is None:
        return None
    source = "api_key" if api_key is not None else "api_key (from TAMRM_API_KEY)"
    if not key or not all(33 <= ord(c) <= 126 for c in key):
        raise ValueError(
            f"{source}: an API key is a non-empty string of printable ASCII without blanks"
        )
    return key


def auth_metadata(
    metadata: Sequence[tuple[str, str]] | None, api_key: str | None
) -> list[tuple[str, str]]:
    """``metadata`` plus ``authorization: Bearer <api_key>`` when there is a key."""
    out = list(metadata or ())
    if api_key is not None:
        if any(k.lower() == "authorization" for k, _ in out):
            raise ValueError("api_key: metadata already holds an authorization header")
        out.append(("authorization", f"Bearer {api_key}"))
    return out


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
    """The task methods of :class:`Client` and :class:`tamrm.Engine`, written once.

    A subclass provides ``_invoke(method, request_bytes) -> response_bytes`` (raising
    ``tamrm._native.StatusError``) and a ``_transport`` that opens sessions.
    """

    _transport: Any

    def _invoke(self, method: str, request: bytes) -> bytes:
        raise NotImplementedError

    def _call(self, rpc: ops.Rpc) -> Any:
        try:
            answer = self._invoke(rpc.method, rpc.request.SerializeToString())
        except _native.StatusError as exc:
            raise from_native(exc) from None
        return _RESPONSES[rpc.method].FromString(answer)

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
        """Open a session for ``num_envs`` environments of a task.

        The stream opens immediately (the answer to ``Open`` is in ``session.task``). Use
        the session as a context manager so that it is closed.

        Raises:
            TaskNotFound: No such task.
            InvalidArgument: ``num_envs`` was rejected.
        """
        return Session(self, task_id, num_envs)


class Client(TaskCalls, Closing):
    """A connection to a tamrm server.

    Every method takes and returns plain Python / numpy values and raises a
    :class:`tamrm.TamrmError` subclass (:class:`tamrm.TaskNotFound`,
    :class:`tamrm.InvalidArgument`, ...) carrying the server's message on failure. The
    transport is native (tonic, in the ``tamrm._native`` extension): a session's round
    trip runs in Rust with the GIL released. :class:`tamrm.Engine` has the same methods
    without a server.

    Example::

        with tamrm.Client("127.0.0.1:50051") as client:
            client.create_task("cartpole", num_actions=2)
            with client.session("cartpole", num_envs=8) as session:
                shaped = session.step(actions, rewards, terminated, truncated)

    A client pickles by its address and settings: the unpickled copy, e.g. in a
    ``SubprocVecEnv`` worker, opens its own connection.

    Args:
        target: The server address, ``host:port`` (surrounding whitespace is ignored).
            Default: the ``TAMRM_ADDRESS`` environment variable, else ``127.0.0.1:50051``.
        timeout: Deadline in seconds of each unary call (``None``: no deadline).
        metadata: Metadata sent with every call.
        api_key: The API key of a server started with ``--api-keys``, sent as
            ``authorization: Bearer <key>`` with every call. Default: the
            ``TAMRM_API_KEY`` environment variable, else none.
    """

    def __init__(
        self,
        target: str | None = None,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        metadata: Sequence[tuple[str, str]] | None = None,
        api_key: str | None = None,
    ) -> None:
        self.target = parse_target(target)
        self.timeout = timeout
        self._metadata = tuple(metadata) if metadata else None
        self._api_key = resolve_api_key(api_key)
        headers = auth_metadata(self._metadata, self._api_key)
        self._transport: _native.Channel
        try:
            self._transport = _native.Channel(self.target, headers)
        except _native.StatusError as exc:
            raise from_native(exc) from None

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled by address and settings: the copy (e.g. in a SubprocVecEnv or
        # AsyncVectorEnv worker) opens its own connection.
        return (_rebuild_client, (self.target, self.timeout, self._metadata, self._api_key))

    def __deepcopy__(self, memo: dict[int, object]) -> Client:
        # A handle on a connection, like the sessions: deep copies are the same client.
        return self

    def _invoke(self, method: str, request: bytes) -> bytes:
        return self._transport.call(method, request, self.timeout)

    # -- lifecycle -------------------------------------------------------------------

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until a connection to the server can be established.

        Raises:
            Unavailable: Not connected within ``timeout`` seconds.
        """
        try:
            self._transport.wait_ready(timeout)
        except _native.StatusError as exc:
            raise from_native(exc) from None

    def close(self) -> None:
        """Close the client (its connection closes once its sessions are closed too)."""

    def __repr__(self) -> str:
        return f"<tamrm.Client target={self.target!r}>"
