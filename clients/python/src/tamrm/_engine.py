"""The embedded engine: tamrm's shaping in-process, without a server."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from tamrm import _bridge
from tamrm._calls import TaskCalls, Timeout
from tamrm._closing import Closing
from tamrm._errors import from_native

__all__ = ["Engine"]


class Engine(TaskCalls, Closing):
    """The shaping engine in this process: the methods of :class:`tamrm.Client`, no server.

    The server's own registry, stores and session layer run in-process (Rust, in the
    ``tamrm._native`` extension); a session's step is one native call with the GIL
    released. Every method, argument, result and error is the same as
    :class:`tamrm.Client`'s, and so are the wrappers (:mod:`tamrm.gym`, :mod:`tamrm.sb3`),
    which take either.

    Example::

        engine = tamrm.Engine()  # in memory; tamrm.Engine("runs/pools") keeps the pools
        engine.create_task("cartpole", num_actions=2)
        with engine.session("cartpole", num_envs=8) as session:
            shaped = session.step(actions, rewards, terminated, truncated)

    Args:
        data_dir: A data directory in the format of ``tamrm serve --data-dir`` (a data dir
            written by one opens in the other), created if missing; every pool change is
            durable before a step returns. ``None``: in memory. The directory is locked
            while the engine is open: a second engine or server on it fails with
            :class:`tamrm.FailedPrecondition`.

    Raises:
        FailedPrecondition: The data dir is in use by another process, or cannot be read.

    An engine lives in one process: it does not pickle (a ``SubprocVecEnv`` worker needs a
    server, ``tamrm serve``, shared through :class:`tamrm.Client`). It is released when
    the last reference to it and to its sessions is gone (:meth:`close` persists the task
    counters).
    """

    def __init__(self, data_dir: str | os.PathLike[str] | None = None) -> None:
        self.data_dir = None if data_dir is None else Path(data_dir)
        self._transport: _bridge.Engine
        try:
            self._transport = _bridge.Engine(None if data_dir is None else os.fspath(data_dir))
        except _bridge.StatusError as exc:
            raise from_native(exc) from None

    def _invoke(self, method: str, request: bytes, timeout: Timeout) -> bytes:
        # In-process: nothing to wait for on a network, so no deadline.
        return self._transport.call(method, request)

    def __reduce__(self) -> tuple[Any, ...]:
        raise TypeError(
            "a tamrm.Engine lives in one process and cannot be pickled; for process-based "
            "vector envs run a server (tamrm serve) and use tamrm.Client"
        )

    def __deepcopy__(self, memo: dict[int, object]) -> Engine:
        return self

    def close(self) -> None:
        """Persist the task counters (pools are durable at every change already)."""
        self._transport.flush()

    def __repr__(self) -> str:
        where = "in memory" if self.data_dir is None else f"data_dir={str(self.data_dir)!r}"
        return f"<tamrm.Engine {where}>"
