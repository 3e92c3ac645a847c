"""How a client connects besides its address: TLS, API key, keepalives, resume, polling.

The keywords of :class:`tamrm.Client` (:class:`ConnectionOptions`), checked and turned
into the native channel's options (:func:`channel_options`) in one place, for the client
and for the local server's health check.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TypedDict

from tamrm import _bridge

__all__ = [
    "DEFAULT_KEEPALIVE_SECS",
    "DEFAULT_KEEPALIVE_TIMEOUT_SECS",
    "DEFAULT_RESUME_TIMEOUT_SECS",
    "MAX_BUSY_POLL_US",
    "ConnectionOptions",
    "Pem",
    "channel_options",
    "read_pem",
    "resolve_api_key",
]

#: Default interval, in seconds, of the client's HTTP/2 keepalive pings.
DEFAULT_KEEPALIVE_SECS = 30.0

#: Default time, in seconds, a keepalive ping may go unanswered before the connection
#: is dropped.
DEFAULT_KEEPALIVE_TIMEOUT_SECS = 20.0

#: How long a session step keeps resuming a broken stream by default (seconds).
DEFAULT_RESUME_TIMEOUT_SECS = 60.0

#: A PEM certificate or key: its contents as ``bytes``, or the path of a PEM file.
Pem = bytes | str | os.PathLike[str]


class ConnectionOptions(TypedDict, total=False):
    """How a client connects, besides its address; the keywords of :class:`tamrm.Client`.

    Every key is optional; see :class:`tamrm.Client` for what each means.
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


def read_pem(name: str, value: Pem | None) -> bytes | None:
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


def channel_options(connection: ConnectionOptions) -> _bridge.ChannelOptions:
    """The native channel's options for ``connection``, checked (``ValueError``)."""
    tls = connection.get("tls")
    pems = {
        "root_certificates": read_pem("root_certificates", connection.get("root_certificates")),
        "certificate_chain": read_pem("certificate_chain", connection.get("certificate_chain")),
        "private_key": read_pem("private_key", connection.get("private_key")),
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
