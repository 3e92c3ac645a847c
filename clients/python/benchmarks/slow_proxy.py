#!/usr/bin/env python3
"""A TCP proxy on 127.0.0.1 that delays what it forwards: a slow path between a learner
and its server (the tests' faults, and a server "on another machine" in the benchmarks).

As a script it forwards to ``TARGET``, prints its own address on one line, and runs until
its standard input closes::

    python benchmarks/slow_proxy.py 127.0.0.1:50051 --delay-ms 1
"""

from __future__ import annotations

import argparse
import contextlib
import queue
import socket
import sys
import threading
import time


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("target", help="the server's address, host:port")
    parser.add_argument("--delay-ms", type=float, default=1.0, help="delay of each direction (ms)")
    ns = parser.parse_args()
    with SlowProxy(ns.target, ns.delay_ms / 1000, ns.delay_ms / 1000) as proxy:
        print(proxy.address, flush=True)
        sys.stdin.read()


if __name__ == "__main__":
    main()
