"""One :class:`tamrm.Client` per process and settings, for the EnvRunners' :class:`KnnShaping`."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

from tamrm._address import parse_targets
from tamrm._client import Client
from tamrm._connection import resolve_api_key

__all__ = ["process_client"]

_CLIENTS: dict[str, Client] = {}
_CLIENTS_LOCK = threading.Lock()


def process_client(
    address: str | Sequence[str] | None = None,
    api_key: str | None = None,
    **connection: Any,
) -> Client:
    """This process's :class:`tamrm.Client` for ``address`` (one per address and settings).

    Every :class:`KnnShaping` of a process (an EnvRunner, its evaluation twin in the same
    process, several pipelines) shares this one client and its connection.

    Args:
        address: The server, as :class:`tamrm.Client` takes it; ``None``: the
            ``TAMRM_ADDRESS`` environment variable of this process, else the default.
        api_key: The API key; ``None``: ``TAMRM_API_KEY`` of this process, else none.
        **connection: Further keywords of :class:`tamrm.Client` (``tls``,
            ``root_certificates``, ``timeout``, ...).
    """
    targets = parse_targets(address)
    key = resolve_api_key(api_key)
    ident = repr((targets, key, sorted(connection.items())))
    with _CLIENTS_LOCK:
        client = _CLIENTS.get(ident)
        if client is None:
            client = _CLIENTS[ident] = Client(list(targets), api_key=key, **connection)
        return client
