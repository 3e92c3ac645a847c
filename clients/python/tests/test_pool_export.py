"""``export_pool`` / ``import_pool`` against the real server and the Engine: a pool moved
through a file shapes every step bit for bit as the one it was exported from, a refused
file changes nothing, and ``replace`` decides what happens to a task that exists."""

from __future__ import annotations

import asyncio
import io
import json
import re
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from test_engine_equivalence import Scenario, random_batch, scenarios, seed_demo

import tamrm
import tamrm.aio

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "pool"
CASES = json.loads((FIXTURES / "cases.json").read_text(encoding="utf-8"))
SHAPED = ("rewards", "knn_rewards", "potentials", "steps", "knn_active", "env_ids")


def new_id() -> str:
    return f"pool/{uuid.uuid4().hex}"


def assert_same_trajectories(got: tamrm.Pool, want: tamrm.Pool) -> None:
    """The same actions and scores, bit for bit, in the same order (seqs may differ)."""
    assert len(got) == len(want)
    for g, w in zip(got.trajectories, want.trajectories, strict=True):
        assert np.float64(g.score).tobytes() == np.float64(w.score).tobytes()
        assert g.actions.dtype == w.actions.dtype and g.actions.shape == w.actions.shape
        assert g.actions.tobytes() == w.actions.tobytes()
    assert [t.seq for t in got.trajectories] == sorted(t.seq for t in got.trajectories)


def export_text(client: tamrm.Client | tamrm.Engine, task_id: str) -> str:
    out = io.StringIO()
    client.export_pool(task_id, out)
    return out.getvalue()


# -- the round trip -------------------------------------------------------------------------


def fill(client: tamrm.Client | tamrm.Engine, task_id: str, sc: Scenario, rng: Any) -> None:
    """Demonstrations, then episodes: inserts, replacements, discards (seqs with gaps)."""
    for _ in range(sc.demos + sc.config["pool_capacity"]):
        client.add_trajectory(task_id, *seed_demo(rng, sc.config))
    num_actions = sc.config.get("num_actions", 0)
    with client.session(task_id, sc.num_envs) as session:
        for _ in range(sc.batches // 2):
            abandon, kwargs = random_batch(rng, sc, num_actions)
            if abandon:
                session.abandon(abandon)
            session.step(**kwargs)


@given(sc=scenarios())
# ``client`` is function-scoped, but only hands out the session's server or engine.
@settings(max_examples=40, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_an_imported_pool_shapes_every_step_as_the_exported_one(
    client: tamrm.Client | tamrm.Engine, engine: tamrm.Engine, sc: Scenario
) -> None:
    rng = np.random.default_rng(sc.seed)
    source = new_id()
    client.create_task(source, **sc.config)
    fill(client, source, sc, rng)
    text = export_text(client, source)
    pool = client.get_pool(source)
    assert len(text.splitlines()) == 1 + len(pool)
    # Into the same backend, and (from a server) into an Engine, under new ids.
    copies = [(client, new_id()), (engine, new_id())]
    for backend, copy in copies:
        task = backend.import_pool(io.StringIO(text), copy)
        assert task.config == client.get_task(source).config
        assert task.stats.pool_size == len(pool)
        assert_same_trajectories(backend.get_pool(copy), pool)
    event(f"{len(pool)} trajectories" if len(pool) else "an empty pool")

    backends = [(client, source), *copies]
    sessions = [b.session(t, sc.num_envs) for b, t in backends]
    try:
        active = 0
        for _ in range(sc.batches):
            abandon, kwargs = random_batch(rng, sc, sc.config.get("num_actions", 0))
            results = []
            for s in sessions:
                if abandon:
                    s.abandon(abandon)
                results.append(s.step(**kwargs))
            for r in results[1:]:
                for name in SHAPED:
                    assert getattr(r, name).tobytes() == getattr(results[0], name).tobytes(), name
            active += int(results[0].knn_active.sum())
    finally:
        for s in sessions:
            s.close()
    event("kNN term active" if active else "kNN term never active")
    # The episodes' ends changed the three pools alike.
    after = [b.get_pool(t) for b, t in backends]
    for p in after[1:]:
        assert_same_trajectories(p, after[0])


def test_the_round_trip_reaches_active_knn_with_a_full_pool(
    client: tamrm.Client | tamrm.Engine, engine: tamrm.Engine
) -> None:
    """The property above is not vacuous: a full pool of tied and differing scores, the kNN
    term active on many steps, and still the same rewards."""
    sc = Scenario(
        config={"num_actions": 2, "pool_capacity": 4, "start_step": 0, "k": 2},
        num_envs=3,
        mode="values",
        demos=4,
        batches=40,
        seed=11,
        end_prob=0.15,
    )
    rng = np.random.default_rng(sc.seed)
    source = new_id()
    client.create_task(source, **sc.config)
    fill(client, source, sc, rng)
    assert client.get_task(source).stats.pool_version > 8  # replacements: seqs have gaps
    copy = new_id()
    engine.import_pool(io.StringIO(export_text(client, source)), copy)
    with client.session(source, 3) as a, engine.session(copy, 3) as b:
        active = 0
        for _ in range(sc.batches):
            _, kwargs = random_batch(rng, sc, 2)
            ra, rb = a.step(**kwargs), b.step(**kwargs)
            assert ra.rewards.tobytes() == rb.rewards.tobytes()
            active += int(ra.knn_active.sum())
    assert active > 20


@pytest.mark.parametrize("name", sorted(CASES["valid"]))
def test_a_fixture_imports_and_exports_again_as_written(
    client: tamrm.Client | tamrm.Engine, name: str
) -> None:
    want = CASES["valid"][name]
    copy = new_id()
    task = client.import_pool(FIXTURES / name, copy)
    assert {f: getattr(task.config, f) for f in tamrm.CONFIG_FIELDS} == want["config"]
    assert task.stats.pool_version == len(want["trajectories"])  # its own inserts, not the file's

    def normalised(text: str, task_id: str) -> list[str]:
        text = re.sub(r'"(seq|pool_version)": \d+', r'"\1": _', text)
        return text.replace(json.dumps(task_id), '"_"').splitlines()

    original = (FIXTURES / name).read_text(encoding="utf-8")
    written = export_text(client, copy)
    assert normalised(written, copy) == normalised(original, want["task_id"])


def test_the_default_task_is_the_files(client: tamrm.Client | tamrm.Engine) -> None:
    source = new_id()
    client.create_task(source, action_dim=2, pool_capacity=3)
    client.add_trajectory(source, np.array([[0.1, 0.2]], np.float32), 1.0)
    text = export_text(client, source)
    client.delete_task(source)
    task = client.import_pool(io.StringIO(text))
    assert task.task_id == source and task.stats.pool_size == 1


def test_export_to_a_path_and_import_from_it(
    client: tamrm.Client | tamrm.Engine, tmp_path: Path
) -> None:
    source = new_id()
    client.create_task(source, num_actions=3, pool_capacity=2)
    client.add_trajectory(source, [2, 1, 0], 4.0)
    path = tmp_path / "pool.jsonl"
    assert client.export_pool(source, path) == 1
    assert client.export_pool(source, str(path)) == 1  # replaced whole
    assert path.read_text(encoding="utf-8") == export_text(client, source)
    copy = new_id()
    client.import_pool(str(path), copy)
    assert_same_trajectories(client.get_pool(copy), client.get_pool(source))


def test_export_of_an_unknown_task(client: tamrm.Client | tamrm.Engine, tmp_path: Path) -> None:
    with pytest.raises(tamrm.TaskNotFound):
        client.export_pool(new_id(), tmp_path / "x.jsonl")
    assert not list(tmp_path.iterdir())


# -- refusals: nothing imported -----------------------------------------------------------


@pytest.mark.parametrize("name", sorted(CASES["refused"]))
def test_a_refused_file_creates_no_task_and_changes_no_pool(
    client: tamrm.Client | tamrm.Engine, name: str
) -> None:
    line = CASES["refused"][name]["line"]
    fresh = new_id()
    with pytest.raises(tamrm.PoolFileError, match=f", line {line}: "):
        client.import_pool(FIXTURES / name, fresh)
    with pytest.raises(tamrm.TaskNotFound):
        client.get_task(fresh)
    # An existing task, even with replace=True: its pool stays as it was.
    existing = new_id()
    client.create_task(existing, num_actions=4, pool_capacity=2)
    client.add_trajectory(existing, [1, 2, 3], 5.0)
    before = client.get_pool(existing)
    with pytest.raises(tamrm.PoolFileError) as info:
        client.import_pool(FIXTURES / name, existing, replace=True)
    assert info.value.line == line
    after = client.get_pool(existing)
    assert after.pool_version == before.pool_version
    assert_same_trajectories(after, before)
    assert client.get_task(existing).config.pool_capacity == 2


# -- a task that exists ----------------------------------------------------------------------


@pytest.fixture
def exported(client: tamrm.Client | tamrm.Engine) -> str:
    """A discrete pool of two trajectories (capacity 3, k 2), exported."""
    source = new_id()
    client.create_task(source, num_actions=3, pool_capacity=3, k=2)
    client.add_trajectory(source, [0, 1], 1.0)
    client.add_trajectory(source, [2], -1.0)
    return export_text(client, source)


def test_another_config_is_refused_unless_replaced(
    client: tamrm.Client | tamrm.Engine, exported: str
) -> None:
    target = new_id()
    client.create_task(target, num_actions=3, pool_capacity=3, k=1, alpha=0.5)
    client.add_trajectory(target, [1, 1, 1], 9.0)
    before = client.get_pool(target)
    with pytest.raises(tamrm.AlreadyExists) as info:
        client.import_pool(io.StringIO(exported), target)
    assert "k: task 1, file 2" in str(info.value) and "alpha: task 0.5, file 0.8" in str(info.value)
    assert "replace=True" in str(info.value)
    assert client.get_task(target).config.k == 1
    assert_same_trajectories(client.get_pool(target), before)

    with client.session(target) as session:
        task = client.import_pool(io.StringIO(exported), target, replace=True)
        assert (task.config.k, task.config.alpha) == (2, 0.8)
        assert task.stats.pool_size == 2 and task.stats.pool_version == 2  # a new task
        with pytest.raises((tamrm.TaskNotFound, tamrm.SessionClosed)):
            session.step([0], [0.0])  # the deleted task's session
    assert client.get_pool(target).scores.tolist() == [1.0, -1.0]


def same_config_task(client: tamrm.Client | tamrm.Engine, *trajectories: Any) -> str:
    """A new task of the exported pool's config, holding ``trajectories``."""
    target = new_id()
    client.create_task(target, num_actions=3, pool_capacity=3, k=2)
    for actions, score in trajectories:
        client.add_trajectory(target, actions, score)
    return target


def test_a_non_empty_pool_is_refused_unless_replaced(
    client: tamrm.Client | tamrm.Engine, exported: str
) -> None:
    target = same_config_task(client, ([1, 1, 1], 9.0))
    with pytest.raises(tamrm.FailedPrecondition, match="already holds 1 trajectory;"):
        client.import_pool(io.StringIO(exported), target)
    assert client.get_pool(target).scores.tolist() == [9.0]
    task = client.import_pool(io.StringIO(exported), target, replace=True)
    # Same config: the pool is reset (one version), then two inserts.
    assert task.stats.pool_version == 1 + 1 + 2
    assert client.get_pool(target).scores.tolist() == [1.0, -1.0]


def test_an_empty_pool_of_the_same_config_takes_the_file(
    client: tamrm.Client | tamrm.Engine, exported: str
) -> None:
    target = same_config_task(client, ([1], 0.0))
    client.reset_pool(target)
    task = client.import_pool(io.StringIO(exported), target)
    assert task.stats.pool_version == 2 + 2
    assert client.get_pool(target).scores.tolist() == [1.0, -1.0]


def test_a_writer_meanwhile_fails_the_import(
    client: tamrm.Client | tamrm.Engine, exported: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = new_id()
    add = client.add_trajectory

    def add_and_another(task_id: str, actions: Any, score: float, **kw: Any) -> Any:
        add(task_id, [0, 0, 0], 100.0)  # a session's episode end, say
        return add(task_id, actions, score, **kw)

    monkeypatch.setattr(client, "add_trajectory", add_and_another)
    with pytest.raises(tamrm.FailedPrecondition, match="changed during the import"):
        client.import_pool(io.StringIO(exported), target)


def test_arguments_are_checked(client: tamrm.Client | tamrm.Engine, exported: str) -> None:
    with pytest.raises(TypeError, match="replace"):
        client.import_pool(io.StringIO(exported), replace=1)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="task_id"):
        client.import_pool(io.StringIO(exported), 7)  # type: ignore[arg-type]


def test_aio_exports_and_imports(server: tamrm.LocalServer, tmp_path: Path) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as client:
            source, copy = new_id(), new_id()
            await client.create_task(source, num_actions=2, pool_capacity=2)
            await client.add_trajectory(source, [1, 0, 1], 3.0)
            assert await client.export_pool(source, tmp_path / "p.jsonl") == 1
            task = await client.import_pool(tmp_path / "p.jsonl", copy)
            assert task.stats.pool_size == 1
            with pytest.raises(tamrm.FailedPrecondition):
                await client.import_pool(tmp_path / "p.jsonl", copy)
            await client.import_pool(tmp_path / "p.jsonl", copy, replace=True)

    asyncio.run(main())
