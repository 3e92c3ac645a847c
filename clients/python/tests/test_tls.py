"""TLS, mutual TLS, keepalive and deadlines of ``tamrm.Client`` / ``tamrm.aio.Client``.

Real ``tamrm serve`` processes with certificates made in the test (``trustme``), and a
raw socket that accepts connections and never answers, for deadlines.
"""

from __future__ import annotations

import asyncio
import pickle
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trustme

import tamrm
import tamrm.aio


@dataclass
class Pki:
    ca: trustme.CA
    ca_pem: bytes
    ca_path: Path
    cert_path: Path
    key_path: Path
    clients_ca_path: Path
    client_cert: bytes
    client_key: bytes
    stranger_cert: bytes
    stranger_key: bytes
    other_ca_pem: bytes


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    tmp = tmp_path_factory.mktemp("pki")
    ca = trustme.CA()
    leaf = ca.issue_cert("localhost", "127.0.0.1")
    clients = trustme.CA()
    client = clients.issue_cert("trainer@example.com")
    stranger = trustme.CA().issue_cert("trainer@example.com")
    ca.cert_pem.write_to_path(str(tmp / "ca.crt"))
    leaf.private_key_pem.write_to_path(str(tmp / "server.key"))
    with open(tmp / "server.crt", "wb") as f:
        for blob in leaf.cert_chain_pems:
            f.write(blob.bytes())
    clients.cert_pem.write_to_path(str(tmp / "clients-ca.crt"))
    return Pki(
        ca=ca,
        ca_pem=ca.cert_pem.bytes(),
        ca_path=tmp / "ca.crt",
        cert_path=tmp / "server.crt",
        key_path=tmp / "server.key",
        clients_ca_path=tmp / "clients-ca.crt",
        client_cert=b"".join(b.bytes() for b in client.cert_chain_pems),
        client_key=client.private_key_pem.bytes(),
        stranger_cert=b"".join(b.bytes() for b in stranger.cert_chain_pems),
        stranger_key=stranger.private_key_pem.bytes(),
        other_ca_pem=trustme.CA().cert_pem.bytes(),
    )


@pytest.fixture(scope="module")
def tls_server(server_binary: str, pki: Pki) -> Iterator[tamrm.LocalServer]:
    args = ["--tls-cert", str(pki.cert_path), "--tls-key", str(pki.key_path)]
    with tamrm.local_server(
        binary=server_binary,
        in_memory=True,
        args=args,
        connection={"root_certificates": pki.ca_pem},
    ) as srv:
        yield srv


@pytest.fixture(scope="module")
def mtls_server(server_binary: str, pki: Pki) -> Iterator[tamrm.LocalServer]:
    args = [
        "--tls-cert",
        str(pki.cert_path),
        "--tls-key",
        str(pki.key_path),
        "--tls-client-ca",
        str(pki.clients_ca_path),
    ]
    connection: tamrm.ConnectionOptions = {
        "root_certificates": pki.ca_pem,
        "certificate_chain": pki.client_cert,
        "private_key": pki.client_key,
    }
    with tamrm.local_server(
        binary=server_binary, in_memory=True, args=args, connection=connection
    ) as srv:
        yield srv


def _shape_once(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, num_envs=1) as session:
        result = session.step(np.array([1]), np.array([1.0]), np.array([True]))
    assert result.rewards.shape == (1,)


def test_a_tls_server_says_so_in_its_log(tls_server: tamrm.LocalServer) -> None:
    assert "TLS on" in tls_server.log()


def test_root_certificates_as_bytes_or_path(
    tls_server: tamrm.LocalServer, pki: Pki, task_id: str
) -> None:
    with tamrm.Client(tls_server.address, root_certificates=pki.ca_pem) as client:
        assert client.tls
        _shape_once(client, task_id)
    with tamrm.Client(tls_server.address, root_certificates=pki.ca_path) as client:
        assert client.get_task(task_id).task_id == task_id
    with tamrm.Client(tls_server.address, root_certificates=str(pki.ca_path)) as client:
        client.wait_ready(10)
        assert "tls" in repr(client)


def test_tls_server_name_overrides_the_host(tls_server: tamrm.LocalServer, pki: Pki) -> None:
    ok = tamrm.Client(tls_server.address, root_certificates=pki.ca_pem, tls_server_name="localhost")
    assert isinstance(ok.list_tasks(), list)
    wrong = tamrm.Client(
        tls_server.address, root_certificates=pki.ca_pem, tls_server_name="elsewhere.example"
    )
    with pytest.raises(tamrm.Unavailable, match="TLS handshake"):
        wrong.list_tasks(timeout=20)


def test_a_wrong_ca_fails_with_a_tls_error_not_a_hang(
    tls_server: tamrm.LocalServer, pki: Pki
) -> None:
    client = tamrm.Client(tls_server.address, root_certificates=pki.other_ca_pem)
    start = time.monotonic()
    with pytest.raises(tamrm.Unavailable) as info:
        client.list_tasks(timeout=None)
    assert "TLS handshake" in str(info.value) and "certificate" in str(info.value)
    assert time.monotonic() - start < 20
    with pytest.raises(tamrm.Unavailable, match="TLS handshake"):
        client.wait_ready(20)
    with pytest.raises(tamrm.Unavailable, match="TLS handshake"):
        client.session("any", num_envs=1)


def test_plaintext_against_tls_and_tls_against_plaintext_fail_clearly(
    tls_server: tamrm.LocalServer, server: tamrm.LocalServer, pki: Pki
) -> None:
    plain = tamrm.Client(tls_server.address)
    with pytest.raises(tamrm.TamrmError) as info:
        plain.list_tasks(timeout=20)
    assert info.value.code is tamrm.StatusCode.UNAVAILABLE
    assert "TLS" in str(info.value), str(info.value)

    tls = tamrm.Client(server.address, root_certificates=pki.ca_pem)
    with pytest.raises(tamrm.Unavailable, match="TLS"):
        tls.list_tasks(timeout=20)


def test_mutual_tls_needs_a_certificate_of_the_client_ca(
    mtls_server: tamrm.LocalServer, pki: Pki, task_id: str
) -> None:
    assert "mutual TLS on" in mtls_server.log()
    no_cert = tamrm.Client(mtls_server.address, root_certificates=pki.ca_pem)
    with pytest.raises(tamrm.Unavailable, match="TLS"):
        no_cert.list_tasks(timeout=20)
    stranger = tamrm.Client(
        mtls_server.address,
        root_certificates=pki.ca_pem,
        certificate_chain=pki.stranger_cert,
        private_key=pki.stranger_key,
    )
    with pytest.raises(tamrm.Unavailable, match="TLS"):
        stranger.list_tasks(timeout=20)
    with mtls_server.client() as client:
        _shape_once(client, task_id)


def test_aio_client_speaks_tls_and_mutual_tls(
    tls_server: tamrm.LocalServer, mtls_server: tamrm.LocalServer, pki: Pki, task_id: str
) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(tls_server.address, root_certificates=pki.ca_pem) as c:
            assert c.tls
            await c.create_task(task_id, num_actions=2)
            async with c.session(task_id, num_envs=1) as session:
                await session.step(np.array([0]), np.array([0.5]), np.array([True]))
            assert (await c.get_task(task_id, timeout=10)).task_id == task_id
        async with tamrm.aio.Client(
            mtls_server.address,
            root_certificates=pki.ca_pem,
            certificate_chain=pki.client_cert,
            private_key=pki.client_key,
        ) as c:
            assert isinstance(await c.list_tasks(), list)
        wrong = tamrm.aio.Client(tls_server.address, root_certificates=pki.other_ca_pem)
        with pytest.raises(tamrm.Unavailable, match="TLS handshake"):
            await wrong.list_tasks()

    asyncio.run(main())


def test_a_tls_client_pickles_with_its_certificates(
    mtls_server: tamrm.LocalServer, pki: Pki
) -> None:
    client = tamrm.Client(
        mtls_server.address,
        root_certificates=pki.ca_path,
        certificate_chain=pki.client_cert,
        private_key=pki.client_key,
        keepalive_secs=5,
        timeout=7,
    )
    copy = pickle.loads(pickle.dumps(client))
    assert copy.tls and copy.timeout == 7
    assert isinstance(copy.list_tasks(), list)
    acopy = pickle.loads(pickle.dumps(tamrm.aio.Client(mtls_server.address, **client._connection)))
    assert asyncio.run(acopy.list_tasks()) == copy.list_tasks()


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"root_certificates": b"not a pem"}, ValueError, "root_certificates"),
        ({"root_certificates": "/nonexistent/ca.crt"}, ValueError, "cannot read"),
        ({"root_certificates": "-----BEGIN CERTIFICATE-----\n"}, TypeError, "bytes"),
        ({"root_certificates": 42}, TypeError, "PEM bytes or the path"),
        ({"certificate_chain": b"x"}, ValueError, "go together"),
        ({"tls": False, "root_certificates": b"x"}, ValueError, "tls=False"),
        ({"tls_server_name": "localhost"}, ValueError, "needs TLS"),
        ({"keepalive_secs": 0}, ValueError, "keepalive_secs"),
        ({"keepalive_timeout_secs": float("nan")}, ValueError, "keepalive_timeout_secs"),
        ({"metadata": [("bad key", "v")]}, ValueError, "metadata key"),
    ],
)
def test_bad_connection_options_fail_at_construction(
    kwargs: tamrm.ConnectionOptions, error: type[Exception], match: str
) -> None:
    with pytest.raises(error, match=match):
        tamrm.Client("127.0.0.1:1", **kwargs)


def test_a_bad_private_key_fails_at_construction(pki: Pki) -> None:
    with pytest.raises(ValueError, match="private_key"):
        tamrm.Client("127.0.0.1:1", certificate_chain=pki.client_cert, private_key=b"nope")


def test_keepalive_options_are_accepted(server: tamrm.LocalServer) -> None:
    with tamrm.Client(server.address, keepalive_secs=1, keepalive_timeout_secs=5) as c:
        assert isinstance(c.list_tasks(), list)
        time.sleep(2.5)  # pings go out and are answered: the connection stays usable
        assert isinstance(c.list_tasks(), list)
    with tamrm.Client(server.address, keepalive_secs=None) as c:
        assert isinstance(c.list_tasks(), list)


@pytest.fixture
def silent_address() -> Iterator[str]:
    """A listening socket that accepts connections and never answers a byte."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    try:
        yield f"127.0.0.1:{listener.getsockname()[1]}"
    finally:
        listener.close()


def test_deadline_exceeded_on_a_server_that_never_answers(silent_address: str) -> None:
    client = tamrm.Client(silent_address, timeout=0.5)
    with pytest.raises(tamrm.DeadlineExceeded) as info:
        client.list_tasks()
    assert info.value.code is tamrm.StatusCode.DEADLINE_EXCEEDED
    start = time.monotonic()
    with pytest.raises(tamrm.DeadlineExceeded):
        client.get_task("x", timeout=1.0)
    assert time.monotonic() - start < 15
    with pytest.raises(tamrm.DeadlineExceeded):
        tamrm.Client(silent_address, timeout=None).get_task("x", timeout=0.3)


def test_deadline_exceeded_through_tls_and_aio(silent_address: str, pki: Pki) -> None:
    client = tamrm.Client(silent_address, root_certificates=pki.ca_pem, timeout=0.5)
    with pytest.raises(tamrm.DeadlineExceeded):
        client.list_tasks()

    async def main() -> None:
        c = tamrm.aio.Client(silent_address, timeout=30)
        with pytest.raises(tamrm.DeadlineExceeded):
            await c.get_pool("x", timeout=0.5)

    asyncio.run(main())


def test_engine_accepts_and_ignores_a_timeout(engine: tamrm.Engine, task_id: str) -> None:
    engine.create_task(task_id, num_actions=2, timeout=0.001)
    assert engine.get_task(task_id, timeout=None).task_id == task_id
