"""Helpers for tests of ``Shape`` streams: the server's count of a task's open streams,
and sessions run in threads at once."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from slow_proxy import SlowProxy  # benchmarks/, on pytest's pythonpath

import tamrm

__all__ = ["SlowProxy", "in_threads", "open_streams"]


def open_streams(client: tamrm.Client, task_id: str, want: int, timeout: float = 10.0) -> int:
    """The task's open streams, waiting up to ``timeout`` s for the server to count ``want``."""
    deadline = time.monotonic() + timeout
    while True:
        n = client.get_task(task_id).stats.open_streams
        if n == want or time.monotonic() > deadline:
            return n
        time.sleep(0.02)


def in_threads(run: Callable[[int], None], n: int, timeout: float = 60.0) -> None:
    """``run(0)`` ... ``run(n - 1)`` in ``n`` threads at once; re-raises the first error,
    and fails if a thread is still running after ``timeout`` s (a hang)."""
    errors: list[BaseException] = []

    def guarded(i: int) -> None:
        try:
            run(i)
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=guarded, args=(i,)) for i in range(n)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout)
    if errors:
        raise errors[0]
    assert not any(thread.is_alive() for thread in threads), "a thread still runs (a hang)"
