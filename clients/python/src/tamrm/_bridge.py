"""The one door to the native extension, ``tamrm._native`` (Rust, ``clients/python/native``).

Every other module of the package reaches the extension through this one, so that what
the Python side uses of it is listed here, once, and ``_native.pyi`` (the extension's
types) is the only description of it to keep in step with the Rust code; a test
(``tests/test_layout.py``) fails when another module imports ``tamrm._native`` or when
the stub and the built extension disagree.

What crosses:

- :class:`Engine`: the server's registry, stores and session layer in this process
  (behind :class:`tamrm.Engine`).
- :class:`Channel`, :class:`ChannelOptions`, :data:`MAX_BUSY_POLL_US`: the gRPC client
  of ``tamrm-client`` (behind :class:`tamrm.Client` and the local server's health check).
- :class:`NativeStream`: one open session stream, of either (behind
  :class:`tamrm.Session`).
- :class:`Mlp`, :class:`VecStep`, :func:`record_step`: Stable-Baselines3's fast path
  (:mod:`tamrm.sb3`).
- ``__version__``: the version the extension was built as (the workspace's, as the
  package's; :data:`tamrm.__version__`).
- :class:`StatusError`: every failed call; ``tamrm._errors.from_native`` turns it into a
  :class:`tamrm.TamrmError`.
"""

from __future__ import annotations

from tamrm._native import (
    MAX_BUSY_POLL_US,
    Channel,
    ChannelOptions,
    Engine,
    Mlp,
    NativeStream,
    StatusError,
    VecStep,
    record_step,
)
from tamrm._native import __version__ as VERSION

__all__ = [
    "VERSION",
    "MAX_BUSY_POLL_US",
    "Channel",
    "ChannelOptions",
    "Engine",
    "Mlp",
    "NativeStream",
    "StatusError",
    "VecStep",
    "record_step",
]
