"""API keys and tenants (SPEC §11) through the Python clients, against the real binary
started with ``--api-keys``."""

from __future__ import annotations

import asyncio
import hashlib
import pickle
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import tamrm
import tamrm.aio

KEYS = {
    ("team-a", "writer"): "key-a-writer",
    ("team-a", "reader"): "key-a-reader",
    ("team-b", "admin"): "key-b-admin",
}


def _key_file(path: Path) -> Path:
    lines = []
    for (tenant, role), key in KEYS.items():
        digest = hashlib.sha256(key.encode()).hexdigest()
        lines += ["[[keys]]", f'tenant = "{tenant}"', f'role = "{role}"', f'sha256 = "{digest}"']
    lines += ["[tenants.team-a]", "max_tasks = 2"]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def keyed_server(server_binary: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    keys = _key_file(tmp_path_factory.mktemp("keys") / "keys.toml")
    with tamrm.local_server(
        binary=server_binary, in_memory=True, args=["--api-keys", str(keys)]
    ) as srv:
        yield srv.address


def test_no_key_or_an_unknown_key_is_unauthenticated(
    keyed_server: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("TAMRM_API_KEY", raising=False)
    with tamrm.Client(keyed_server) as c, pytest.raises(tamrm.TamrmError) as err:
        c.list_tasks()
    assert isinstance(err.value, tamrm.Unauthenticated)
    with tamrm.Client(keyed_server, api_key="nope") as c, pytest.raises(tamrm.TamrmError) as err:
        c.list_tasks()
    assert isinstance(err.value, tamrm.Unauthenticated)
    assert "nope" not in str(err.value)


def test_roles_and_tenants(keyed_server: str) -> None:
    writer = tamrm.Client(keyed_server, api_key=KEYS[("team-a", "writer")])
    reader = tamrm.Client(keyed_server, api_key=KEYS[("team-a", "reader")])
    other = tamrm.Client(keyed_server, api_key=KEYS[("team-b", "admin")])
    with writer, reader, other:
        writer.create_task("cartpole", num_actions=2, pool_capacity=4, min_pool_size=1)
        other.create_task("cartpole", num_actions=3)
        assert reader.get_task("cartpole").config.num_actions == 2
        assert other.get_task("cartpole").config.num_actions == 3
        assert [t.task_id for t in reader.list_tasks()] == ["cartpole"]
        with pytest.raises(tamrm.TamrmError) as err:
            reader.create_task("mine", num_actions=2)
        assert isinstance(err.value, tamrm.PermissionDenied)
        with pytest.raises(tamrm.TamrmError) as err:
            writer.delete_task("cartpole")
        assert isinstance(err.value, tamrm.PermissionDenied)
        # Shaping through a session: the pool of team-a's cartpole changes, team-b's not.
        with writer.session("cartpole", num_envs=2) as s:
            out = s.step(np.array([1, 0]), np.array([1.0, 2.0]), np.array([True, True]))
            assert out.rewards.shape == (2,)
        assert len(reader.get_pool("cartpole").trajectories) > 0
        assert len(other.get_pool("cartpole").trajectories) == 0
        with pytest.raises(tamrm.TaskNotFound):
            other.get_pool("nothing-here")
        # Quotas: team-a holds at most 2 tasks.
        writer.create_task("second", num_actions=2)
        with pytest.raises(tamrm.TamrmError) as err:
            writer.create_task("third", num_actions=2)
        assert err.value.code == tamrm.StatusCode.RESOURCE_EXHAUSTED
        assert "max_tasks = 2" in str(err.value)


def test_the_key_comes_from_the_environment_and_survives_pickling(
    keyed_server: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TAMRM_API_KEY", KEYS[("team-a", "reader")])
    with tamrm.Client(keyed_server) as c:
        c.list_tasks()
        assert "key-a-reader" not in repr(c)
        copy = pickle.loads(pickle.dumps(c))
    monkeypatch.delenv("TAMRM_API_KEY")
    with copy:
        copy.list_tasks()


def test_asyncio_client_takes_the_key(keyed_server: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(keyed_server, api_key=KEYS[("team-b", "admin")]) as c:
            await c.create_task("async-task", num_actions=2)
            assert "async-task" in [t.task_id for t in await c.list_tasks()]
            await c.delete_task("async-task")

    asyncio.run(main())


def test_a_key_that_cannot_be_a_header_is_refused_early(keyed_server: str) -> None:
    with pytest.raises(ValueError, match="api_key"):
        tamrm.Client(keyed_server, api_key="two\nlines")
    with pytest.raises(ValueError, match="api_key"):
        tamrm.Client(keyed_server, api_key="")
