"""A :class:`tamrm.Engine` across a pickle, within its process.

SuperSuit copies an env by pickling it, even to use the copy in the same process; an
engine does not pickle. A pickled wrapper holds a mark of its engine instead, which the
copy turns back into the engine while both live in this process.
"""

from __future__ import annotations

import itertools
import os
import weakref

from tamrm._client import Client
from tamrm._engine import Engine

__all__ = ["pickled_api", "unpickled_api"]

# Engines pickled by a wrapper in this process (SuperSuit copies an env by pickling it,
# even to use it in the same process): the copy finds its engine here by number.
_ENGINE_KEYS: weakref.WeakKeyDictionary[Engine, int] = weakref.WeakKeyDictionary()
_ENGINES: weakref.WeakValueDictionary[int, Engine] = weakref.WeakValueDictionary()
_NEXT_ENGINE_KEY = itertools.count(1)


def pickled_api(api: Engine | Client) -> object:
    """What a pickled wrapper holds for ``api``: the client, or a same-process engine mark."""
    if not isinstance(api, Engine):
        return api
    key = _ENGINE_KEYS.get(api)
    if key is None:
        key = next(_NEXT_ENGINE_KEY)
        _ENGINE_KEYS[api] = key
        _ENGINES[key] = api
    return ("tamrm.Engine", os.getpid(), key)


def unpickled_api(held: object) -> Engine | Client:
    if not isinstance(held, tuple):
        assert isinstance(held, (Engine, Client))
        return held
    _, pid, key = held
    engine = _ENGINES.get(key) if pid == os.getpid() else None
    if engine is None:
        raise TypeError(
            "a tamrm.Engine lives in one process: a wrapper on it can be copied (or pickled "
            "and unpickled) in that process only, while the engine exists; for worker "
            "processes (SuperSuit's num_cpus > 0, RLlib's env runners) run a server "
            "(tamrm serve) and pass a tamrm.Client"
        )
    return engine
