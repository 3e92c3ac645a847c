"""Where a client connects: the address (or addresses) given, checked, or ``$TAMRM_ADDRESS``."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence

__all__ = [
    "ADDRESS_ENV",
    "DEFAULT_ADDRESS",
    "Targets",
    "parse_target",
    "parse_targets",
]

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
