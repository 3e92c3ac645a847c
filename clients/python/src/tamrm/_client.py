"""The synchronous client: a connection to a tamrm server (:class:`Client`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tamrm import _bridge
from tamrm._address import ADDRESS_ENV, DEFAULT_ADDRESS, Targets, parse_target, parse_targets
from tamrm._calls import CLIENT_TIMEOUT, DEFAULT_TIMEOUT, TaskCalls, Timeout
from tamrm._closing import Closing
from tamrm._connection import (
    DEFAULT_KEEPALIVE_SECS,
    DEFAULT_KEEPALIVE_TIMEOUT_SECS,
    DEFAULT_RESUME_TIMEOUT_SECS,
    ConnectionOptions,
    Pem,
    channel_options,
    read_pem,
    resolve_api_key,
)
from tamrm._errors import from_native

# Client, and the names of its address, connection options and calls, which their own
# modules hold (importable from here too).
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


def _rebuild_client(
    target: Targets, timeout: float | None, connection: ConnectionOptions
) -> Client:
    return Client(target, timeout=timeout, **connection)


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
            "root_certificates": read_pem("root_certificates", root_certificates),
            "certificate_chain": read_pem("certificate_chain", certificate_chain),
            "private_key": read_pem("private_key", private_key),
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
            self._transport = _bridge.Channel(list(self.targets), channel_options(connection))
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
