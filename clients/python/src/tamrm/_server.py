"""Start a local ``tamrm`` server for tests, examples and notebooks."""

from __future__ import annotations

import importlib.metadata
import os
import re
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tamrm import _bridge

if TYPE_CHECKING:
    from tamrm._connection import ConnectionOptions

__all__ = [
    "LocalServer",
    "ServerStartError",
    "find_binary",
    "health_check",
    "installed_binary",
    "local_server",
]

_LISTENING = re.compile(r"listening on (\S+)")
_ADDRESS = re.compile(r"^\s*(\S+):(\d+)\s*$")


class ServerStartError(RuntimeError):
    """The ``tamrm`` binary could not be found, or did not start and become healthy."""


def _executable(path: Path) -> bool:
    return path.is_file() and os.access(path, os.X_OK)


def installed_binary() -> Path | None:
    """The server binary the wheel installed as the ``tamrm`` command, if it did.

    Found through the package's own record of its files, so a ``tamrm`` of another
    installation earlier on ``PATH`` is never taken for it.
    """
    try:
        files = importlib.metadata.distribution("tamrm").files or []
    except importlib.metadata.PackageNotFoundError:
        return None
    for file in files:
        if file.name == "tamrm" and file.parent.name in ("bin", "Scripts"):
            path = Path(str(file.locate())).resolve()
            if _executable(path):
                return path
    return None


def find_binary() -> Path:
    """Locate the ``tamrm`` server binary.

    Looked up, in order: the ``TAMRM_BIN`` environment variable, the binary the wheel
    installed, ``tamrm`` on ``PATH``, then ``target/release/tamrm`` in the repository this
    package (or the current directory) lives in.

    Raises:
        ServerStartError: Not found (or ``TAMRM_BIN`` is not an executable file).
    """
    env = os.environ.get("TAMRM_BIN")
    if env:
        path = Path(env).expanduser()
        if not _executable(path):
            raise ServerStartError(f"TAMRM_BIN={env} is not an executable file")
        return path.resolve()
    installed = installed_binary()
    if installed is not None:
        return installed
    found = shutil.which("tamrm")
    if found:
        return Path(found).resolve()
    starts = [Path(__file__).resolve().parent, Path.cwd().resolve()]
    for start in starts:
        for directory in (start, *start.parents):
            candidate = directory / "target" / "release" / "tamrm"
            if _executable(candidate):
                return candidate
    raise ServerStartError(
        "tamrm binary not found: install the tamrm wheel (it has the server), set "
        "TAMRM_BIN, put tamrm on PATH, or build it with `cargo build --release` in the "
        "repository"
    )


def health_check(
    target: str,
    service: str = "",
    timeout: float = 2.0,
    connection: ConnectionOptions | None = None,
) -> bool:
    """Ask ``grpc.health.v1.Health/Check`` whether ``service`` is SERVING at ``target``.

    ``connection`` holds the client's TLS settings for a TLS server (the keywords of
    :class:`tamrm.Client`). Returns ``False`` on any error.
    """
    from tamrm._connection import channel_options

    try:
        options = channel_options(connection or {})
        return _bridge.Channel([target], options).health(service, timeout)
    except (ValueError, TypeError, _bridge.StatusError):
        return False


@dataclass
class LocalServer:
    """A ``tamrm`` server process started by :func:`local_server`.

    Attributes:
        address: The bound address, ``127.0.0.1:PORT``.
        data_dir: The server's data directory (``None`` for an in-memory server).
        process: The server process.
        log_path: The file receiving the server's stdout and stderr.
        connection: How clients connect (TLS settings), the keywords of
            :class:`tamrm.Client` that :meth:`client` passes.
    """

    address: str
    data_dir: Path | None
    process: subprocess.Popen[bytes]
    log_path: Path
    connection: ConnectionOptions = field(default_factory=dict)  # type: ignore[assignment]
    _clients: list[Any] = field(default_factory=list, repr=False)

    @property
    def target(self) -> str:
        """The gRPC target to connect to (same as :attr:`address`)."""
        return self.address

    @property
    def port(self) -> int:
        """The bound TCP port."""
        return int(self.address.rsplit(":", 1)[1])

    def client(self, **kwargs: Any) -> Any:
        """Return a :class:`tamrm.Client` connected to this server (closed on stop).

        It connects with :attr:`connection`, overridden by ``kwargs``.
        """
        from tamrm._client import Client

        client = Client(self.address, **{**self.connection, **kwargs})
        self._clients.append(client)
        return client

    def log(self) -> str:
        """Return the server's output so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, timeout: float = 10.0) -> int | None:
        """Stop the server (SIGTERM, then SIGKILL after ``timeout`` s); return its exit code."""
        for client in self._clients:
            client.close()
        self._clients.clear()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode


def _read_address(port_file: Path, log_path: Path) -> str | None:
    try:
        match = _ADDRESS.match(port_file.read_text())
    except OSError:
        match = None
    if match:
        host, port = match.groups()
    else:
        try:
            found = _LISTENING.search(log_path.read_text(errors="replace"))
        except OSError:
            found = None
        if not found:
            return None
        hostport = _ADDRESS.match(found.group(1))
        if not hostport:
            return None
        host, port = hostport.groups()
    if host in ("0.0.0.0", "[::]", "::"):
        host = "127.0.0.1"
    return f"{host}:{port}"


@contextmanager
def local_server(
    *,
    binary: str | os.PathLike[str] | None = None,
    data_dir: str | os.PathLike[str] | None = None,
    listen: str = "127.0.0.1:0",
    args: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
    startup_timeout: float = 60.0,
    in_memory: bool = False,
    connection: ConnectionOptions | None = None,
) -> Iterator[LocalServer]:
    """Run a ``tamrm`` server for the duration of a ``with`` block.

    Starts ``tamrm serve --listen 127.0.0.1:0 --data-dir DIR --port-file FILE`` (a free
    port, a temporary data directory unless ``data_dir`` is given), waits until the
    bound address is known and the gRPC health service reports SERVING, and stops the
    process on exit. The binary is ``binary`` or :func:`find_binary`'s.

    Example::

        with tamrm.local_server() as server, tamrm.Client(server.address) as client:
            client.create_task("demo", num_actions=4)

    Args:
        binary: Path of the ``tamrm`` binary.
        data_dir: The server's data directory (kept); default a temporary one (removed).
        listen: The ``--listen`` address.
        args: Extra command-line arguments for ``tamrm serve``.
        env: Extra environment variables for the server process.
        startup_timeout: Seconds to wait for the server to become healthy.
        in_memory: Start the server without ``--data-dir`` (tasks and pools in memory
            only, nothing fsynced); ``data_dir`` must then be ``None``.
        connection: How to connect to it, the keywords of :class:`tamrm.Client` (e.g.
            ``root_certificates=`` for a server started with ``--tls-cert``): used for
            the health check and by :meth:`LocalServer.client`.

    Raises:
        ServerStartError: No binary, or the server exited or did not become healthy in
            time (the message includes the end of its log).
    """
    if in_memory and data_dir is not None:
        raise ValueError("in_memory=True and data_dir are exclusive")
    exe = Path(binary) if binary is not None else find_binary()
    if not _executable(exe):
        raise ServerStartError(f"{exe} is not an executable file")
    with tempfile.TemporaryDirectory(prefix="tamrm-") as tmp:
        tmp_path = Path(tmp)
        data = Path(data_dir) if data_dir is not None else tmp_path / "data"
        port_file = tmp_path / "port"
        log_path = tmp_path / "server.log"
        cmd = [str(exe), "serve", "--listen", listen]
        if not in_memory:
            data.mkdir(parents=True, exist_ok=True)
            cmd += ["--data-dir", str(data)]
        cmd += ["--port-file", str(port_file), *args]
        proc_env = dict(os.environ)
        if env:
            proc_env.update(env)
        with open(log_path, "wb") as log:
            process = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=proc_env
            )
        server: LocalServer | None = None
        try:
            address = None
            deadline = time.monotonic() + startup_timeout
            while time.monotonic() < deadline:
                if process.poll() is not None:
                    break
                address = _read_address(port_file, log_path)
                if address is not None and health_check(address, "", 1.0, connection):
                    break
                time.sleep(0.05)
            else:
                address = None
            if address is None or process.poll() is not None:
                tail = log_path.read_text(errors="replace")[-4000:]
                state = (
                    f"exited with code {process.returncode}"
                    if process.poll() is not None
                    else f"not healthy after {startup_timeout}s"
                )
                raise ServerStartError(f"tamrm server {state}: {' '.join(cmd)}\n{tail}")
            server = LocalServer(
                address=address,
                data_dir=None if in_memory else data,
                process=process,
                log_path=log_path,
                connection=connection or {},
            )
            yield server
        finally:
            if server is not None:
                server.stop()
            elif process.poll() is None:
                process.kill()
                process.wait()
