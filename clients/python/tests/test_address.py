"""Client addresses: whitespace, malformed addresses, ``TAMRM_ADDRESS``."""

from __future__ import annotations

import asyncio

import pytest

import tamrm
import tamrm.aio


def test_address_with_newline_from_port_file(server: tamrm.LocalServer, task_id: str) -> None:
    # What `cat port-file` gives: the address and a newline.
    with tamrm.Client(f"  {server.address}\n") as client:
        assert client.target == server.address
        client.create_task(task_id, num_actions=2)
        with client.session(task_id) as session:
            assert session.step([1], [1.0]).rewards.shape == (1,)


@pytest.mark.parametrize(
    ("address", "says"),
    [
        ("http://127.0.0.1:50051", "'127.0.0.1:50051' without the scheme"),
        ("https://localhost:50051/", "URL"),
        ("grpc://localhost:50051", "URL"),
        ("127.0.0.1", "no port"),
        ("localhost", "no port"),
        ("127.0.0.1:", "not an address"),
        (":50051", "not an address"),
        ("127.0.0.1:99999", "not in 1..65535"),
        ("127.0.0.1:0", "not in 1..65535"),
        ("local host:50051", "not an address"),
        ("", "not an address"),
        ("127.0.0.1:50051:1", "not an address"),
    ],
)
def test_malformed_address_is_rejected_at_construction(address: str, says: str) -> None:
    for make in (tamrm.Client, tamrm.aio.Client):
        with pytest.raises(ValueError, match="expected host:port") as info:
            make(address)
        assert says in str(info.value)


def test_accepted_forms() -> None:
    for address in ("localhost:50051", "[::1]:50051", "my-host.example.org:1", "unix:/tmp/x"):
        with tamrm.Client(address) as client:
            assert client.target == address


def test_address_not_a_string() -> None:
    with pytest.raises(TypeError, match="host:port"):
        tamrm.Client(50051)  # type: ignore[arg-type]


def test_tamrm_address_is_the_default(
    server: tamrm.LocalServer, task_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TAMRM_ADDRESS", server.address + "\n")
    with tamrm.Client() as client:
        assert client.target == server.address
        client.create_task(task_id, num_actions=2)

    async def main() -> list[str]:
        async with tamrm.aio.Client() as aclient:
            return [t.task_id for t in await aclient.list_tasks()]

    assert task_id in asyncio.run(main())
    monkeypatch.setenv("TAMRM_ADDRESS", "http://" + server.address)
    with pytest.raises(ValueError, match=r"\$TAMRM_ADDRESS .*expected host:port"):
        tamrm.Client()


def test_no_address_no_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TAMRM_ADDRESS", raising=False)
    with tamrm.Client() as client:
        assert client.target == tamrm.DEFAULT_ADDRESS
