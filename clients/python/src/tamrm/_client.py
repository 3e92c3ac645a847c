"""The synchronous client."""

from __future__ import annotations

import enum
import functools
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, TypeVar

import numpy.typing as npt
from google.protobuf import message_factory
from google.protobuf.message import Message

from tamrm import _bridge
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
    "CLIENT_TIMEOUT",
    "DEFAULT_ADDRESS",
    "DEFAULT_KEEPALIVE_SECS",
    "DEFAULT_KEEPALIVE_TIMEOUT_SECS",
    "DEFAULT_TIMEOUT",
    "Client",
    "ConnectionOptions",
    "Pem",
    "TaskCalls",
    "Timeout",
    "parse_target",
    "parse_targets",
]

#: Default deadline, in seconds, of every unary call (not of ``Shape`` streams).
DEFAULT_TIMEOUT = 30.0

#: Default interval, in seconds, of the client's HTTP/2 keepalive pings.
DEFAULT_KEEPALIVE_SECS = 30.0

#: Default time, in seconds, a keepalive ping may go unanswered before the connection
#: is dropped.
DEFAULT_KEEPALIVE_TIMEOUT_SECS = 20.0

#: How long a session step keeps resuming a broken stream by default (seconds).
DEFAULT_RESUME_TIMEOUT_SECS = 60.0


class _ClientTimeout(enum.Enum):
    TIMEOUT = "the client's timeout"


#: The default of a call's ``timeout=``: the deadline given to the client.
CLIENT_TIMEOUT = _ClientTimeout.TIMEOUT

#: A call's deadline: seconds, ``None`` for none, or :data:`CLIENT_TIMEOUT`.
Timeout = float | None | _ClientTimeout

#: A PEM certificate or key: its contents as ``bytes``, or the path of a PEM file.
Pem = bytes | str | os.PathLike[str]


class ConnectionOptions(TypedDict, total=False):
    """How a client connects, besides its address; the keywords of :class:`Client`.

    Every key is optional; see :class:`Client` for what each means.
    """

    metadata: Sequence[tuple[str, str]] | None
    tls: bool | None
    root_certificates: Pem | None
    certificate_chain: Pem | None
    private_key: Pem | None
    tls_server_name: str | None
    keepalive_secs: float | None
    keepalive_timeout_secs: float
    api_key: str | None
    resume_timeout_secs: float | None
    busy_poll_us: int


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


#: What :class:`Client` takes as its target: one address, or several (replicas sharing
#: one store, tried in turn).
Targets = str | Sequence[str]


def parse_targets(target: Targets | None) -> tuple[str, ...]:
    """Return the gRPC targets of ``target``: one address, or a sequence of several.

    ``None``: ``$TAMRM_ADDRESS``, which may name several addresses separated by commas
    (``host1:50051,host2:50051``), else the default. Each address is checked as by
    :func:`parse_target`.

    Raises:
        TypeError: Not a string or a sequence of strings.
        ValueError: An empty sequence, or a malformed address (the message names it).
    """
    if target is None:
        env = os.environ.get(ADDRESS_ENV)
        if env is not None and "," in env:
            parts = [p for p in env.split(",") if p.strip()]
            if not parts:
                raise ValueError(f"${ADDRESS_ENV} {env!r} names no address")
            return tuple(parse_target(p) for p in parts)
        return (parse_target(None),)
    if isinstance(target, str):
        return (parse_target(target),)
    if not isinstance(target, Sequence):
        raise TypeError(
            f"target must be a str 'host:port' or a sequence of them, got {type(target).__name__}"
        )
    targets = tuple(parse_target(t) for t in target)
    if not targets:
        raise ValueError("target: an empty sequence names no server; give at least one address")
    return targets


_T = TypeVar("_T")


def _rebuild_client(
    target: Targets, timeout: float | None, connection: ConnectionOptions
) -> Client:
    return Client(target, timeout=timeout, **connection)


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


def _auth_metadata(
    metadata: Sequence[tuple[str, str]] | None, api_key: str | None
) -> list[tuple[str, str]]:
    """``metadata`` plus ``authorization: Bearer <api_key>`` when there is a key."""
    out = [(str(k), str(v)) for k, v in metadata or ()]
    if api_key is not None:
        if any(k.lower() == "authorization" for k, _ in out):
            raise ValueError("api_key: metadata already holds an authorization header")
        out.append(("authorization", f"Bearer {api_key}"))
    return out


#: The longest ``busy_poll_us`` a client takes (one second), the native extension's bound.
MAX_BUSY_POLL_US: int = _bridge.MAX_BUSY_POLL_US


def _busy_poll_us(value: object) -> int:
    """``busy_poll_us``, checked: an int from 0 to :data:`MAX_BUSY_POLL_US`."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"busy_poll_us must be an int (microseconds), got {type(value).__name__}")
    if not 0 <= value <= MAX_BUSY_POLL_US:
        raise ValueError(
            f"busy_poll_us must be from 0 (off) to {MAX_BUSY_POLL_US} (one second), got {value}"
        )
    return value


def _optional_seconds(value: float | None) -> float | None:
    """``None`` or 0 for "off", else the value as a float."""
    return None if value is None or value == 0 else float(value)


def _read_pem(name: str, value: Pem | None) -> bytes | None:
    """The PEM bytes of ``value``: bytes as they are, a path's file contents."""
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, str) and value.lstrip().startswith("-----BEGIN"):
        raise TypeError(f"{name} is PEM text: pass it as bytes (a str is the path of a PEM file)")
    if isinstance(value, (str, os.PathLike)):
        try:
            return Path(value).read_bytes()
        except OSError as exc:
            raise ValueError(f"{name}: cannot read {os.fspath(value)!r}: {exc}") from None
    raise TypeError(
        f"{name} must be PEM bytes or the path of a PEM file, got {type(value).__name__}"
    )


def _channel_options(connection: ConnectionOptions) -> _bridge.ChannelOptions:
    """The native channel's options for ``connection``, checked (``ValueError``)."""
    tls = connection.get("tls")
    pems = {
        "root_certificates": _read_pem("root_certificates", connection.get("root_certificates")),
        "certificate_chain": _read_pem("certificate_chain", connection.get("certificate_chain")),
        "private_key": _read_pem("private_key", connection.get("private_key")),
    }
    if tls is False and any(v is not None for v in pems.values()):
        raise ValueError("tls=False contradicts root_certificates/certificate_chain/private_key")
    keepalive = connection.get("keepalive_secs", DEFAULT_KEEPALIVE_SECS)
    return _bridge.ChannelOptions(
        metadata=_auth_metadata(connection.get("metadata"), connection.get("api_key")),
        tls=bool(tls),
        root_certificates=pems["root_certificates"],
        certificate_chain=pems["certificate_chain"],
        private_key=pems["private_key"],
        server_name=connection.get("tls_server_name"),
        keepalive_secs=None if keepalive is None else float(keepalive),
        keepalive_timeout_secs=float(
            connection.get("keepalive_timeout_secs", DEFAULT_KEEPALIVE_TIMEOUT_SECS)
        ),
        resume_timeout_secs=_optional_seconds(
            connection.get("resume_timeout_secs", DEFAULT_RESUME_TIMEOUT_SECS)
        ),
        busy_poll_us=_busy_poll_us(connection.get("busy_poll_us", 0)),
    )


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

    A client pickles by its address and settings (certificates and keys included, read
    once at construction): the unpickled copy, e.g. in a ``SubprocVecEnv`` worker, opens
    its own connection.

    Args:
        target: The server address, ``host:port`` (surrounding whitespace is ignored),
            or a sequence of several: replicas sharing one store (``tamrm serve
            --store redis://...``, docs/scaling.md). Calls go to the first; when it
            cannot be reached, to the next, and a session whose server goes away resumes
            on the next one. Default: the ``TAMRM_ADDRESS`` environment variable (one
            address, or several separated by commas), else ``127.0.0.1:50051``.
        timeout: Default deadline in seconds of each unary call (``None``: no deadline);
            each method's ``timeout=`` overrides it for one call. Not applied to
            ``Shape`` streams (sessions).
        metadata: Metadata (e.g. an authorization header) sent with every call.
        tls: ``True``: connect with TLS; without ``root_certificates`` the system's CA
            store verifies the server. Default: TLS when a certificate is given, else
            plaintext. ``False`` with a certificate is a ``ValueError``.
        root_certificates: PEM CA certificate(s) that verify the server (turns TLS on).
        certificate_chain: PEM client certificate for a mutual-TLS server, with
            ``private_key``.
        private_key: PEM private key of ``certificate_chain``.
        tls_server_name: The name the server's certificate must be valid for, when it
            is not the host of ``target`` (grpcio's ``ssl_target_name_override``).
        keepalive_secs: Interval of HTTP/2 keepalive pings on an active connection
            (``None``: no pings). A ping unanswered for ``keepalive_timeout_secs``
            drops the connection, so a dead server is noticed within their sum.
        keepalive_timeout_secs: See ``keepalive_secs``.
        resume_timeout_secs: When a session's stream breaks (the server restarted,
            went away, or answered ``UNAVAILABLE``), ``Session.step`` reconnects with
            exponential backoff, re-opens the stream resuming every environment's
            episode (SPEC §9), re-sends the batch and returns its answer, for up to this
            many seconds; then it raises :class:`tamrm.Unavailable`. ``None`` or 0:
            fail at once.
        api_key: The API key of a server started with ``--api-keys``, sent as
            ``authorization: Bearer <key>`` with every call. Default: the
            ``TAMRM_API_KEY`` environment variable, else none.
        busy_poll_us: How long ``Session.step`` polls for its answer, in microseconds,
            before it sleeps until the answer comes (0, the default: it sleeps at once).
            Polling keeps the calling thread's CPU awake, which on a machine whose idle
            CPUs are slow to wake (a VM) cuts the round trip to a server on the same host
            or a near one: SB3 A2C through a local server went from +49 % to +38 %
            overhead with 200 (docs/python-performance.md, "Overhead"). The price is
            that CPU, busy for up to this long on every step: worth it when the training
            loop has nothing else to do while it waits, not for a server far away (a
            round trip longer than the poll gains nothing). At most 1 000 000.

    Each PEM argument is the file's contents as ``bytes``, or the path of the file
    (``str`` or ``os.PathLike``), read once here. A malformed PEM, or a path that cannot
    be read, is a ``ValueError`` here, not a failed call later.
    """

    def __init__(
        self,
        target: Targets | None = None,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        metadata: Sequence[tuple[str, str]] | None = None,
        tls: bool | None = None,
        root_certificates: Pem | None = None,
        certificate_chain: Pem | None = None,
        private_key: Pem | None = None,
        tls_server_name: str | None = None,
        keepalive_secs: float | None = DEFAULT_KEEPALIVE_SECS,
        keepalive_timeout_secs: float = DEFAULT_KEEPALIVE_TIMEOUT_SECS,
        api_key: str | None = None,
        resume_timeout_secs: float | None = DEFAULT_RESUME_TIMEOUT_SECS,
        busy_poll_us: int = 0,
    ) -> None:
        self.targets = parse_targets(target)
        #: The first address (every address: :attr:`targets`).
        self.target = self.targets[0]
        self.timeout = timeout
        connection: ConnectionOptions = {
            "metadata": tuple(metadata) if metadata else None,
            "tls": tls,
            "root_certificates": _read_pem("root_certificates", root_certificates),
            "certificate_chain": _read_pem("certificate_chain", certificate_chain),
            "private_key": _read_pem("private_key", private_key),
            "tls_server_name": tls_server_name,
            "keepalive_secs": keepalive_secs,
            "keepalive_timeout_secs": keepalive_timeout_secs,
            "api_key": resolve_api_key(api_key),
            "resume_timeout_secs": resume_timeout_secs,
            "busy_poll_us": busy_poll_us,
        }
        self._connection = connection
        self._transport: _bridge.Channel
        try:
            self._transport = _bridge.Channel(list(self.targets), _channel_options(connection))
        except _bridge.StatusError as exc:
            raise from_native(exc) from None

    @property
    def tls(self) -> bool:
        """Whether the client connects with TLS."""
        return bool(self._transport.tls)

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled by address and settings: the copy (e.g. in a SubprocVecEnv or
        # AsyncVectorEnv worker) opens its own connection.
        return (_rebuild_client, (self.targets, self.timeout, self._connection))

    def __deepcopy__(self, memo: dict[int, object]) -> Client:
        # A handle on a connection, like the sessions: deep copies are the same client.
        return self

    def _invoke(self, method: str, request: bytes, timeout: Timeout) -> bytes:
        if timeout is CLIENT_TIMEOUT:
            timeout = self.timeout
        return self._transport.call(method, request, timeout)

    # -- lifecycle -------------------------------------------------------------------

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until a connection to the server can be established.

        Raises:
            Unavailable: Not connected within ``timeout`` seconds.
        """
        try:
            self._transport.wait_ready(timeout)
        except _bridge.StatusError as exc:
            raise from_native(exc) from None

    def close(self) -> None:
        """Close the client (its connection closes once its sessions are closed too)."""

    def __repr__(self) -> str:
        tls = " tls" if self.tls else ""
        where = f"target={self.target!r}" if len(self.targets) == 1 else f"targets={self.targets!r}"
        return f"<tamrm.Client {where}{tls}>"
