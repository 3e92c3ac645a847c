"""Waiting for the server's count of a task's open ``Shape`` streams."""

from __future__ import annotations

import time

import tamrm


def open_streams(client: tamrm.Client, task_id: str, want: int, timeout: float = 10.0) -> int:
    """The task's open streams, waiting up to ``timeout`` s for the server to count ``want``."""
    deadline = time.monotonic() + timeout
    while True:
        n = client.get_task(task_id).stats.open_streams
        if n == want or time.monotonic() > deadline:
            return n
        time.sleep(0.02)
