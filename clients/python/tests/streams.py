"""Helpers for tests of ``Shape`` streams: the server's count of a task's open streams,
and sessions run in threads at once."""

from __future__ import annotations

import contextlib
import queue
import socket
import threading
import time
from collections.abc import Callable

import tamrm


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


class SlowProxy:
    """A TCP proxy on 127.0.0.1 that forwards what the server sends ``delay`` seconds late
    and what the client sends ``up_delay`` seconds late (each in order): a slow path
    between server and learner. ``address`` is the proxy's; ``sever()`` cuts the
    connections open now, dropping what they still carry (new ones are forwarded as
    before); use it as a context manager."""

    def __init__(self, target: str, delay: float, up_delay: float = 0.0) -> None:
        host, port = target.rsplit(":", 1)
        self._target = (host, int(port))
        self._delay = delay
        self._up_delay = up_delay
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"127.0.0.1:{self._listener.getsockname()[1]}"
        self._connections: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                down, _ = self._listener.accept()
            except OSError:
                return
            up = socket.create_connection(self._target)
            for s in (down, up):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._connections += [down, up]
            for src, dst, delay in ((down, up, self._up_delay), (up, down, self._delay)):
                late: queue.Queue[tuple[float, bytes]] = queue.Queue()
                threading.Thread(target=self._pump, args=(src, late, delay), daemon=True).start()
                threading.Thread(target=self._late, args=(late, dst), daemon=True).start()

    def _pump(
        self, src: socket.socket, late: queue.Queue[tuple[float, bytes]], delay: float
    ) -> None:
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                data = b""
            late.put((time.monotonic() + delay, data))
            if not data:
                return

    def _late(self, late: queue.Queue[tuple[float, bytes]], dst: socket.socket) -> None:
        while True:
            at, data = late.get()
            time.sleep(max(0.0, at - time.monotonic()))
            try:
                if not data:
                    dst.shutdown(socket.SHUT_WR)
                    return
                dst.sendall(data)
            except OSError:
                return

    def sever(self) -> None:
        """Closes the connections open now (both ends): what they still carry is lost."""
        connections, self._connections = self._connections, []
        for s in connections:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()

    def __enter__(self) -> SlowProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.sever()
        with contextlib.suppress(OSError):
            self._listener.close()
