"""Local sessions (SPEC §13): ``client.session(task_id, n, local=True)`` shapes in this
process against a copy of the server's pool that follows it (a ``Follow`` stream), and
sends only its episode ends. Against the real server binary:

- a local session and a remote one on twin tasks answer every step bit for bit alike, and
  leave the same pools (random scenarios, a second session opened mid-run);
- several local learners on one task: counters add up, versions never go back, and one
  learner's pool change reaches the others within a bounded wait;
- a server killed and restarted under a local session: it goes on with the rewards of an
  uninterrupted run, and no end is committed twice;
- errors are a remote session's; the gymnasium and SB3 wrappers (fast path, pickled into
  a ``SubprocVecEnv`` worker) take local sessions.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import pickle
import re
import shutil
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from streams import SlowProxy, in_threads, open_streams
from test_engine_equivalence import (
    Scenario,
    assert_results_identical,
    outcome,
    random_batch,
    reject_alike,
    scenarios,
    seed_demo,
)
from test_failover import _replica

import tamrm
import tamrm.aio
import tamrm.gym

#: How long another learner's pool change may take to reach a local session's copy.
STALENESS_WAIT = 5.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def assert_pools_equal(got: tamrm.Pool, want: tamrm.Pool) -> None:
    """Two pools (of twin tasks) hold the same trajectories: version, seqs, scores and
    actions, bit for bit."""
    assert got.pool_version == want.pool_version
    a, b = got.trajectories, want.trajectories
    assert [(t.seq, t.score) for t in a] == [(t.seq, t.score) for t in b]
    for x, y in zip(a, b, strict=True):
        assert x.actions.dtype == y.actions.dtype and x.actions.shape == y.actions.shape
        assert x.actions.tobytes() == y.actions.tobytes(), x.seq


def assert_stats_equal(got: tamrm.Task, want: tamrm.Task) -> None:
    """Twin tasks' statistics agree (but ``open_streams``)."""
    a, b = dataclasses.asdict(got.stats), dataclasses.asdict(want.stats)
    a.pop("open_streams")
    b.pop("open_streams")
    assert a == b


# -- a local session is bit for bit a remote one ------------------------------------------


@dataclasses.dataclass
class Pair:
    """A local session and a remote one, each on its twin task, fed the same batches.

    Each has one environment more than the scenario's: the *probe* environment, stepped
    (on both) while the local session's copy of the pool catches up with a change made
    by another session or by ``add_trajectory`` (SPEC §13: within the staleness bound).
    Its episode never ends, so it changes no pool; its answers are not compared.
    """

    local: tamrm.Session
    remote: tamrm.Session
    sc: Scenario  # num_envs: the environments the batches use (the probe not counted)

    @property
    def both(self) -> tuple[tamrm.Session, tamrm.Session]:
        return self.local, self.remote

    def catch_up(self, version: int) -> int:
        """Step the probe until the local session's copy holds ``version``; the number of
        probe steps."""
        deadline = time.monotonic() + STALENESS_WAIT
        probes = 0
        probe = np.array([self.sc.num_envs], dtype=np.int64)
        config = self.local.config
        action: Any = [0] if config.discrete else np.zeros((1, config.action_dim))
        while self.local.pool_version < version:
            assert time.monotonic() < deadline, (self.local.pool_version, version)
            if probes:
                time.sleep(0.002)
            for s in self.both:
                s.step(action, [0.0], env_ids=probe)
            probes += 1
        return probes

    def close(self) -> None:
        for s in self.both:
            s.close()


def _twin_tasks(client: tamrm.Client, config: dict[str, Any]) -> tuple[str, str]:
    base = f"local/{uuid.uuid4().hex}"
    local, remote = f"{base}/local", f"{base}/remote"
    tasks = [client.create_task(t, **config) for t in (local, remote)]
    assert tasks[0].config == tasks[1].config
    return local, remote


def _open_pair(client: tamrm.Client, ids: tuple[str, str], sc: Scenario) -> Pair:
    local = client.session(ids[0], sc.num_envs + 1, local=True)
    remote = client.session(ids[1], sc.num_envs + 1)
    assert local.local and not remote.local
    assert local.config == remote.config
    assert local.pool_version == remote.pool_version
    return Pair(local, remote, sc)


def run_twins(
    client: tamrm.Client, sc: Scenario, second_at: int | None, second_envs: int
) -> dict[str, int]:
    """Feed ``sc`` to a local and a remote session on twin tasks (and, from batch
    ``second_at`` on, to a second pair of ``second_envs`` environments, the batches going
    to either pair at random); every answer must be the same. Returns what the run went
    through."""
    seen = {"active": 0, "nonzero_knn": 0, "rejected": 0, "caught_up": 0, "second": 0}
    ids = _twin_tasks(client, sc.config)
    rng = np.random.default_rng(sc.seed)
    # The server's pool version, as the local side last learnt it.
    latest = 0
    for _ in range(sc.demos):
        actions, score = seed_demo(rng, sc.config)
        added = [client.add_trajectory(t, actions, score) for t in ids]
        assert added[0] == added[1], added
        latest = added[0].pool_version
    pairs = [_open_pair(client, ids, sc)]
    num_actions = pairs[0].local.config.num_actions
    try:
        for i in range(sc.batches):
            if i == second_at:
                pairs.append(_open_pair(client, ids, dataclasses.replace(sc, num_envs=second_envs)))
            if rng.random() < 0.04:  # seed the pools while the sessions are open
                actions, score = seed_demo(rng, sc.config)
                added = [client.add_trajectory(t, actions, score) for t in ids]
                assert added[0] == added[1], added
                latest = added[0].pool_version
            pair = pairs[int(rng.integers(len(pairs)))]
            seen["second"] += pair is not pairs[0]
            abandon, kwargs = random_batch(rng, pair.sc, num_actions)
            if kwargs["env_ids"] is None:  # every env but the probe
                kwargs["env_ids"] = np.arange(pair.sc.num_envs)
            if pair.catch_up(latest):
                seen["caught_up"] += 1
            if abandon:
                for s in pair.both:
                    s.abandon(abandon)
            if rng.random() < 0.06 and reject_alike(list(pair.both), kwargs):
                seen["rejected"] += 1
            got, want = (s.step(**kwargs) for s in pair.both)
            assert_results_identical(got, want)
            assert np.array_equal(pair.local.episode_steps, pair.remote.episode_steps)
            latest = max(latest, got.pool_version)
            seen["active"] += int(got.knn_active.sum())
            seen["nonzero_knn"] += int(np.count_nonzero(got.knn_rewards))
    finally:
        for pair in pairs:
            pair.close()
    local_pool, remote_pool = (client.get_pool(t) for t in ids)
    assert_pools_equal(local_pool, remote_pool)
    # The local sessions reported every step they shaped when they closed.
    local_task, remote_task = (client.get_task(t) for t in ids)
    assert_stats_equal(local_task, remote_task)
    assert local_task.stats.pool_size == len(local_pool)
    seen["pool_version"] = local_pool.pool_version
    return seen


@st.composite
def twin_runs(draw: Callable[..., Any]) -> tuple[Scenario, int | None, int]:
    sc = draw(scenarios())
    second_at = draw(st.none() | st.integers(0, sc.batches - 1))
    return sc, second_at, draw(st.integers(1, 3))


@given(run=twin_runs())
@settings(max_examples=50)
def test_local_and_remote_sessions_shape_bit_identically(
    remote_client: tamrm.Client, run: tuple[Scenario, int | None, int]
) -> None:
    seen = run_twins(remote_client, *run)
    event("kNN term active" if seen["active"] else "kNN term never active")
    event("pool changed" if seen["pool_version"] else "pool unchanged")
    event("a copy caught up" if seen["caught_up"] else "no catching up")


def test_the_twin_runs_reach_active_knn_replacements_and_catching_up(
    remote_client: tamrm.Client,
) -> None:
    """The property above is not vacuous: with these settings the kNN term is active,
    episodes replace others in a full pool, a second pair of sessions shapes, and local
    copies had to catch up with changes made by the other session."""
    sc = Scenario(
        config={"num_actions": 2, "pool_capacity": 3, "start_step": 0, "k": 2},
        num_envs=3,
        mode="values",
        demos=3,
        batches=70,
        seed=5,
        end_prob=0.15,
    )
    seen = run_twins(remote_client, sc, second_at=20, second_envs=2)
    assert seen["active"] > 20 and seen["nonzero_knn"] > 10, seen
    assert seen["pool_version"] > sc.demos + 3, seen
    assert seen["second"] > 10 and seen["caught_up"] >= 2, seen
    assert seen["rejected"] >= 1, seen


def test_local_sessions_wait_for_a_score_spread_as_remote_ones(
    remote_client: tamrm.Client,
) -> None:
    """With ``require_score_spread`` (SPEC v1.3) a local session's copy decides where the
    kNN term is active as the server does: not on a pool of equal scores (a change made
    elsewhere that keeps them equal included), then from the episode end that stores
    another score on."""
    config: dict[str, Any] = {
        "num_actions": 2,
        "pool_capacity": 4,
        "k": 4,
        "start_step": 0,
        "min_pool_size": 1,
        "gate_potential": True,
        "require_score_spread": True,
    }
    ids = _twin_tasks(remote_client, config)
    for t in ids:
        remote_client.add_trajectory(t, [0, 0, 0, 0], 1.0)
    sc = Scenario(config, num_envs=1, mode="values", demos=0, batches=0, seed=0, end_prob=0.0)
    pair = _open_pair(remote_client, ids, sc)
    assert pair.local.config.require_score_spread is True
    active: list[bool] = []

    def step_both(action: int, **kwargs: Any) -> tamrm.StepResult:
        got, want = (
            s.step([action], [0.5], values=[1.0], next_values=[4.0], env_ids=[0], **kwargs)
            for s in pair.both
        )
        assert_results_identical(got, want)
        active.append(bool(got.knn_active[0]))
        return got

    try:
        step_both(0)
        # Another equal score, added while the sessions are open: still no spread.
        latest = [remote_client.add_trajectory(t, [1, 1, 1], 1.0) for t in ids]
        assert latest[0] == latest[1]
        pair.catch_up(latest[0].pool_version)
        step_both(0)
        # This episode ends scored 3: stored by both, it is the spread.
        step_both(0, truncated=[True], episode_scores={0: 3.0})
        for _ in range(4):
            step_both(1)
    finally:
        pair.close()
    assert active == [False, False, False, True, True, True, False]
    assert_pools_equal(*(remote_client.get_pool(t) for t in ids))


# -- many learners on one task --------------------------------------------------------------


@pytest.mark.parametrize("capacity", [4, 400], ids=["replacing", "inserting"])
def test_many_local_learners_on_one_task(
    remote_client: tamrm.Client, task_id: str, capacity: int
) -> None:
    """With a small pool the racing ends replace (at most one unanswered change each); in
    a large one they insert (any number unanswered)."""
    client = remote_client
    client.create_task(
        task_id, num_actions=3, pool_capacity=capacity, k=2, start_step=1, min_pool_size=1
    )
    learners = [client.session(task_id, 2, local=True) for _ in range(4)]
    sent = [{"steps": 0, "ends": 0} for _ in learners]
    versions: list[list[int]] = [[s.pool_version] for s in learners]

    def step(i: int, *args: Any, **kwargs: Any) -> tamrm.StepResult:
        out = learners[i].step(*args, **kwargs)
        sent[i]["steps"] += len(out)
        terminated = args[2] if len(args) > 2 else kwargs.get("terminated")
        sent[i]["ends"] += 0 if terminated is None else int(np.sum(terminated))
        versions[i].append(out.pool_version)
        return out

    # One learner's pool change reaches another within a bounded wait: each ends an
    # episode with a score above every stored one (an insert, or a replacement).
    for r in range(8):
        a, b = r % 4, (r + 1) % 4
        before = client.get_task(task_id).stats.pool_version
        changed = step(a, [r % 3, 0], [0.0, 0.0], [True, False], episode_scores={0: 100.0 + r})
        assert changed.pool_version == before + 1
        deadline = time.monotonic() + STALENESS_WAIT
        while step(b, [0, 1], [0.0, 0.0]).pool_version < changed.pool_version:
            assert time.monotonic() < deadline, "another learner's change never arrived"
            time.sleep(0.003)

    def learn(i: int) -> None:
        rng = np.random.default_rng(i)
        for _ in range(150):
            ends = rng.random(2) < 0.12
            scores = np.where(ends, rng.uniform(0, 200, 2), np.nan)
            step(i, rng.integers(0, 3, 2), rng.normal(size=2), ends, episode_scores=scores)

    in_threads(learn, 4)
    # Racing ends made copies plan changes the server decided otherwise; once the acks are
    # in (a call of the client waits for them), every copy holds the server's pool: it
    # shapes fresh episodes as a remote session on the task does.
    latest = client.get_task(task_id).stats.pool_version
    probes = [[0, 1], [2, 2], [1, 0]]
    with client.session(task_id, 2) as remote:
        want = [remote.step(a, [0.0, 0.0]) for a in probes]
    sent[0]["steps"] += sum(len(w) for w in want)
    # (The large pool keeps one-step episodes, so its kNN term stays off at the probes'
    # steps: there they check versions only.)
    assert want[1].knn_active.all() or capacity == 400
    for i, s in enumerate(learners):
        deadline = time.monotonic() + STALENESS_WAIT
        while step(i, [0, 0], [0.0, 0.0]).pool_version < latest:
            assert time.monotonic() < deadline, "a copy never caught up"
            time.sleep(0.003)
        s.abandon([0, 1])
        for a, w in zip(probes, want, strict=True):
            got = step(i, a, [0.0, 0.0])
            assert got.pool_version == w.pool_version == latest
            assert got.knn_rewards.tobytes() == w.knn_rewards.tobytes(), i
    for s in learners:
        s.close()
    for seen in versions:
        assert seen == sorted(seen), "a session's pool version went down"
    stats = client.get_task(task_id).stats
    assert stats.episodes_completed == sum(s["ends"] for s in sent) > 40
    assert stats.steps_shaped == sum(s["steps"] for s in sent)
    assert stats.pool_version >= max(v[-1] for v in versions)
    assert client.get_pool(task_id).pool_version == stats.pool_version


@contextlib.contextmanager
def _late_learner(
    remote_client: tamrm.Client, task_id: str, num_envs: int
) -> Iterator[tuple[tamrm.Client, tamrm.Session]]:
    """A client and its local session on a new task (capacity 2, seeded with scores 0 and
    100) whose updates come 50 ms late: a slow path from the server."""
    config = {"num_actions": 3, "pool_capacity": 2, "k": 2, "start_step": 0, "min_pool_size": 1}
    remote_client.create_task(task_id, **config)
    for score in (0.0, 100.0):
        remote_client.add_trajectory(task_id, [1, 1, 1, 1], score)
    with SlowProxy(remote_client.target, delay=0.05) as proxy:
        client = tamrm.Client(proxy.address)
        learner = client.session(task_id, num_envs, local=True)
        try:
            yield client, learner
        finally:
            learner.close()
            client.close()


def test_a_copy_that_planned_against_a_stale_pool_takes_the_servers(
    remote_client: tamrm.Client, task_id: str
) -> None:
    """A learner whose updates come late (a slow path from the server) ends an episode
    after another client's better trajectory reached the server but not its copy: the
    copy plans a replacement the server refuses, at the version of the server's pool. The
    ack differs from the plan, and the copy takes the server's pool before its next step
    (an update of the same version would not replace it)."""
    with _late_learner(remote_client, task_id, 1) as (client, learner):
        for r in range(4):
            for _ in range(3):
                learner.step([2], [0.0])
            # The server's pool: minimum 100 (r + 1); the copy's: 100 r.
            added = remote_client.add_trajectory(task_id, [0, 0, 0, 0], 100.0 * (r + 2))
            planned = learner.step([2], [0.0], [True], episode_scores=[100.0 * r + 50])
            assert planned.pool_version == added.pool_version, r
            with remote_client.session(task_id, 1) as remote:
                want = remote.step([0], [0.0])
            client.get_task(task_id)  # the end's ack is in
            got = learner.step([0], [0.0])
            assert got.pool_version == want.pool_version == added.pool_version, r
            assert got.knn_rewards.tobytes() == want.knn_rewards.tobytes(), r
            learner.abandon([0])
    pool = remote_client.get_pool(task_id)
    assert [t.score for t in pool.trajectories] == [400.0, 500.0]


#: Two ends scored 50 and 60: in one batch, or in two.
TWO_ENDS = {
    "one batch": [([True, True], [50.0, 60.0])],
    "two batches": [([True, False], {0: 50.0}), ([False, True], {1: 60.0})],
}


@pytest.mark.parametrize("batches", TWO_ENDS.values(), ids=TWO_ENDS.keys())
def test_two_changes_planned_against_a_stale_pool_are_never_shaped_with(
    remote_client: tamrm.Client, task_id: str, batches: list[tuple[list[bool], Any]]
) -> None:
    """Two ends plan two changes against a copy that has not yet seen another client's
    better trajectory; the server refuses both, so its version is one below the plan's. A
    step that reported the plan's version would see the next go down. In one batch, the
    batch waits for the server's decision; in two, the second waits for the first's ack,
    which differs from its plan, and then for its own. Either way the step reports the
    server's version, and the next step shapes with the server's pool."""
    with _late_learner(remote_client, task_id, 2) as (_, learner):
        for _ in range(3):
            learner.step([2, 2], [0.0, 0.0])
        added = remote_client.add_trajectory(task_id, [0, 0, 0, 0], 1000.0)
        for ends, scores in batches:
            ended = learner.step([2, 2], [0.0, 0.0], ends, episode_scores=scores)
            assert ended.pool_version == added.pool_version
        with remote_client.session(task_id, 1) as remote:
            want = remote.step([0], [0.0])
        got = learner.step([0, 0], [0.0, 0.0])
        assert got.pool_version == want.pool_version == added.pool_version
        assert got.knn_rewards[:1].tobytes() == want.knn_rewards.tobytes()
    pool = remote_client.get_pool(task_id)
    assert [t.score for t in pool.trajectories] == [100.0, 1000.0]
    assert remote_client.get_task(task_id).stats.episodes_completed == 2


def test_a_second_change_waits_for_the_first_ack_not_for_its_own(
    remote_client: tamrm.Client, task_id: str
) -> None:
    """A replacement that one change of another learner could make the server refuse
    (it beats only the lowest score), planned while another change is in flight, is sent
    at once, and its step waits for the first one's ack (already on its way), which
    certifies the pool it was planned against, not for its own: the step returns while
    its end is still on the slow path to the server, with the version a ``Shape`` stream
    would report."""
    config = {"num_actions": 3, "pool_capacity": 2, "k": 2, "start_step": 0, "min_pool_size": 1}
    remote_client.create_task(task_id, **config)
    for score in (0.0, 0.5):  # a full pool: every change below replaces
        remote_client.add_trajectory(task_id, [1, 1], score)
    with SlowProxy(remote_client.target, delay=0.0, up_delay=1.5) as proxy:
        client = tamrm.Client(proxy.address)
        learner = client.session(task_id, 1, local=True)
        try:
            learner.step([1], [1.0])
            first = learner.step([1], [1.0], [True], episode_scores=[1.0])
            assert first.pool_version == 3  # answered at once
            time.sleep(0.75)  # the second end reaches the server 0.75 s after the first
            learner.step([1], [1.0])
            second = learner.step([1], [1.0], [True], episode_scores=[0.7])
            assert second.pool_version == 4  # waited for the first's ack
            assert remote_client.get_task(task_id).stats.episodes_completed == 1
            assert client.get_task(task_id).stats.episodes_completed == 2  # waits for the acks
        finally:
            learner.close()
            client.close()


def test_inserts_into_a_pool_with_room_never_wait(
    remote_client: tamrm.Client, task_id: str
) -> None:
    """Ends that plan only inserts (the pool has room) never wait for the server, however
    many are unanswered and however many end in one batch: whatever others change first,
    the server takes them or makes up for them with versions of its own."""
    config = {"num_actions": 3, "pool_capacity": 8, "k": 2, "start_step": 0, "min_pool_size": 1}
    remote_client.create_task(task_id, **config)
    with SlowProxy(remote_client.target, delay=0.0, up_delay=1.5) as proxy:
        client = tamrm.Client(proxy.address)
        learner = client.session(task_id, 3, local=True)
        try:
            versions = []
            for _ in range(2):
                learner.step([1, 1, 1], [1.0, 1.0, 1.0])
                versions.append(learner.step([1, 1, 1], [1.0] * 3, [True] * 3).pool_version)
            assert versions == [3, 6]
            assert remote_client.get_task(task_id).stats.episodes_completed == 0  # on the way
            assert client.get_task(task_id).stats.episodes_completed == 6  # waits for the acks
        finally:
            learner.close()
            client.close()
    assert remote_client.get_pool(task_id).pool_version == 6


def test_replacements_far_above_the_lowest_scores_never_wait(
    remote_client: tamrm.Client, task_id: str
) -> None:
    """Replacements that each beat more of the pool than there are changes unanswered
    (a learner that improves) never wait for the server: as many changes of others as
    that could not make the server refuse one, and more would leave it at a version no
    lower. Replacements that beat only the lowest score of the same pool wait."""
    config = {"num_actions": 3, "pool_capacity": 8, "k": 2, "start_step": 0, "min_pool_size": 1}
    remote_client.create_task(task_id, **config)
    for score in range(8):  # a full pool of low scores: every change below replaces
        remote_client.add_trajectory(task_id, [1, 1], float(score))
    with SlowProxy(remote_client.target, delay=0.0, up_delay=1.5) as proxy:
        client = tamrm.Client(proxy.address)
        learner = client.session(task_id, 2, local=True)
        try:
            versions = []
            for high in (100.0, 200.0):
                learner.step([1, 1], [1.0, 1.0])
                ended = learner.step([1, 1], [1.0] * 2, [True] * 2, episode_scores=[high] * 2)
                versions.append(ended.pool_version)
            assert versions == [10, 12]
            assert remote_client.get_task(task_id).stats.episodes_completed == 0  # on the way
            learner.step([1, 1], [1.0, 1.0])
            started = time.monotonic()
            # 4.5 and 5.5 beat only the lowest scores left (4, then 4.5): they wait.
            low = learner.step([1, 1], [1.0] * 2, [True] * 2, episode_scores=[4.5, 5.5])
            assert time.monotonic() - started > 0.5
            assert low.pool_version == 14
        finally:
            learner.close()
            client.close()
    pool = remote_client.get_pool(task_id)
    assert pool.pool_version == 14
    assert sorted(t.score for t in pool.trajectories) == [5, 5.5, 6, 7, 100, 100, 200, 200]


def test_a_snapshot_behind_an_unanswered_end_does_not_take_the_session_back(
    remote_client: tamrm.Client, task_id: str
) -> None:
    """The stream breaks while an end is on its way to the server (a slow path from the
    learner), so the re-opened stream's snapshot lacks it until the re-sent end arrives.
    That snapshot is behind the session's plan, not a server that lost changes: every
    step shapes on with the plan's version, and the end is committed once."""
    config = {"num_actions": 3, "pool_capacity": 4, "k": 2, "start_step": 0, "min_pool_size": 1}
    remote_client.create_task(task_id, **config)
    with SlowProxy(remote_client.target, delay=0.0, up_delay=0.4) as proxy:
        client = tamrm.Client(proxy.address, resume_timeout_secs=30)
        learner = client.session(task_id, 1, local=True)
        try:
            for _ in range(3):
                learner.step([1], [1.0])
            learner.step([1], [1.0], [True])  # plans the pool's first trajectory
            proxy.sever()  # ...and its message is lost on the way
            seen = []
            committed_at = None
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                seen.append(learner.step([1], [1.0]).pool_version)
                if committed_at is None and remote_client.get_task(task_id).stats.pool_version:
                    committed_at = len(seen)
                if committed_at is not None and len(seen) > committed_at + 10:
                    break
                time.sleep(0.01)
            assert committed_at is not None, "the re-sent end never reached the server"
            assert set(seen) == {1}, f"the session went back to {min(seen)}"
        finally:
            learner.close()
            client.close()
    stats = remote_client.get_task(task_id).stats
    assert (stats.pool_version, stats.episodes_completed) == (1, 1)


# -- resume ------------------------------------------------------------------------------------

NUM_ENVS = 3
RESUME_CONFIG = {"num_actions": 3, "pool_capacity": 4, "k": 2, "start_step": 1, "min_pool_size": 1}


def _batches(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [
        (rng.integers(0, 3, NUM_ENVS), rng.normal(size=NUM_ENVS), rng.random(NUM_ENVS) < 0.2)
        for _ in range(n)
    ]


def test_a_local_session_resumes_across_a_kill_and_restart(
    server_binary: str, tmp_path: Path
) -> None:
    batches = _batches(7, 60)
    # The reference: one uninterrupted session (a learner alone: the values of a Shape
    # stream, which are the engine's).
    with tamrm.Engine() as engine:
        engine.create_task("t", **RESUME_CONFIG)
        with engine.session("t", num_envs=NUM_ENVS) as s:
            want = [s.step(a, r, t).rewards.tobytes() for a, r, t in batches]
        want_pool = engine.get_pool("t")
        want_task = engine.get_task("t")

    listen = f"127.0.0.1:{_free_port()}"
    data = tmp_path / "data"
    restarted: list[Any] = []

    def restart() -> None:
        time.sleep(0.5)
        cm = tamrm.local_server(binary=server_binary, data_dir=data, listen=listen)
        restarted.append((cm, cm.__enter__()))

    with tamrm.local_server(binary=server_binary, data_dir=data, listen=listen) as first:
        client = tamrm.Client(first.address, resume_timeout_secs=30)
        client.create_task("t", **RESUME_CONFIG)
        session = client.session("t", num_envs=NUM_ENVS, local=True)
        got = []
        it = iter(batches)
        # Up to a batch whose episode ends were acknowledged, with episodes in progress.
        for a, r, t in it:
            got.append(session.step(a, r, t).rewards.tobytes())
            if len(got) > 12 and t.any() and session.episodes_in_progress.any():
                break
        acked = client.get_task("t").stats.episodes_completed
        assert acked > 0
        first.process.send_signal(signal.SIGKILL)
        first.process.wait()
        thread = threading.Thread(target=restart)
        thread.start()
        try:
            # Steps are shaped here; the first episode end waits for the restarted server.
            got += [session.step(a, r, t).rewards.tobytes() for a, r, t in it]
        finally:
            thread.join()
            session.close()
            try:
                assert got == want
                # Every end committed once: the pool of a run without kill, and no end
                # counted twice (the server's count of the ends it discarded since its
                # last sync may be lost with kill -9, as under a remote session).
                assert_pools_equal(client.get_pool("t"), want_pool)
                ended = want_task.stats.episodes_completed
                assert ended - acked <= client.get_task("t").stats.episodes_completed <= ended
            finally:
                client.close()
                for cm, _ in restarted:
                    cm.__exit__(None, None, None)


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server is not installed")
def test_a_local_session_fails_over_to_another_replica(server_binary: str, redis_url: str) -> None:
    """Replicas sharing a Redis store (SPEC §10): the Follow stream moves to the next
    address when its replica is killed, and the session goes on as if nothing happened."""
    batches = _batches(3, 60)
    with tamrm.Engine() as engine:
        engine.create_task("t", **RESUME_CONFIG)
        with engine.session("t", num_envs=NUM_ENVS) as s:
            want = [s.step(a, r, t).rewards.tobytes() for a, r, t in batches]
        want_pool = engine.get_pool("t")
    with _replica(server_binary, redis_url) as a, _replica(server_binary, redis_url) as b:
        client = tamrm.Client([a.address, b.address], resume_timeout_secs=30)
        client.create_task("t", **RESUME_CONFIG)
        session = client.session("t", num_envs=NUM_ENVS, local=True)
        got = [session.step(a_, r, t).rewards.tobytes() for a_, r, t in batches[:25]]
        a.process.send_signal(signal.SIGKILL)
        a.process.wait()
        started = time.monotonic()
        got += [session.step(a_, r, t).rewards.tobytes() for a_, r, t in batches[25:]]
        assert time.monotonic() - started < 20
        session.close()
        assert got == want
        assert_pools_equal(client.get_pool("t"), want_pool)
        assert open_streams(client, "t", 0) == 0
        client.close()


def test_without_a_server_an_episode_end_gives_up_after_its_deadline(server_binary: str) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        client = tamrm.Client(srv.address, resume_timeout_secs=1.0)
        client.create_task("t", **RESUME_CONFIG)
        session = client.session("t", num_envs=NUM_ENVS, local=True)
        session.step([0, 1, 2], [1.0, 1.0, 1.0])
        srv.process.send_signal(signal.SIGKILL)
        srv.process.wait()
        # Steps that end no episode need no server.
        session.step([0, 1, 2], [1.0, 1.0, 1.0])
        started = time.monotonic()
        # An episode end is answered with the session's plan and sent without waiting;
        # steps go on until its ack gives up at the deadline, which the next step raises.
        session.step([0, 1, 2], [1.0, 1.0, 1.0], [True, False, False])
        with pytest.raises(tamrm.Unavailable):
            while time.monotonic() - started < 20:
                session.step([0, 1, 2], [1.0, 1.0, 1.0])
                time.sleep(0.02)
        assert 1.0 <= time.monotonic() - started < 20
        assert session.closed
        with pytest.raises(tamrm.SessionClosed):
            session.step([0, 1, 2], [1.0, 1.0, 1.0])
        client.close()


# -- errors ----------------------------------------------------------------------------------


def test_unknown_task_is_task_not_found_as_remote(remote_client: tamrm.Client) -> None:
    remote_client.create_task("local-errors/cartpole", num_actions=2)
    local = outcome(lambda: remote_client.session("local-errors/cartpol", local=True))
    remote = outcome(lambda: remote_client.session("local-errors/cartpol"))
    assert local == remote
    assert local[0] is tamrm.TaskNotFound and "cartpol" in local[1]


def test_a_task_deleted_under_a_local_session(remote_client: tamrm.Client, task_id: str) -> None:
    remote_client.create_task(task_id, num_actions=3)
    session = remote_client.session(task_id, 2, local=True)
    session.step([2, 1], [1.0, 1.0], [True, False])
    remote_client.delete_task(task_id)
    # A step that ends no episode is shaped here, without the server. An episode end
    # fails as a remote session's step does once the server's notice has arrived: at
    # once, or (its end sent before the notice came) at a later step, once the server
    # has refused it.
    session.step([1, 1], [1.0, 1.0])
    deadline = time.monotonic() + 10
    with pytest.raises(tamrm.TaskNotFound, match=re.escape(task_id)):
        while time.monotonic() < deadline:
            session.step([1, 1], [1.0, 1.0], [False, True])
            time.sleep(0.01)
    assert session.closed
    with pytest.raises(tamrm.SessionClosed):
        session.step([1, 1], [1.0, 1.0])
    session.close()


KEYS = {"writer": "local-writer-key", "reader": "local-reader-key"}


@pytest.fixture(scope="module")
def keyed_server(server_binary: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    lines = []
    for role, key in KEYS.items():
        digest = hashlib.sha256(key.encode()).hexdigest()
        lines += ["[[keys]]", 'tenant = "team"', f'role = "{role}"', f'sha256 = "{digest}"']
    keys = tmp_path_factory.mktemp("keys") / "keys.toml"
    keys.write_text("\n".join(lines) + "\n")
    with tamrm.local_server(
        binary=server_binary, in_memory=True, args=["--api-keys", str(keys)]
    ) as srv:
        yield srv.address


def test_a_local_session_needs_a_writer_key(keyed_server: str) -> None:
    writer = tamrm.Client(keyed_server, api_key=KEYS["writer"])
    reader = tamrm.Client(keyed_server, api_key=KEYS["reader"])
    nobody = tamrm.Client(keyed_server, api_key="wrong")
    with writer, reader, nobody:
        writer.create_task("keyed", num_actions=2, pool_capacity=2, min_pool_size=1)
        with pytest.raises(tamrm.PermissionDenied):
            reader.session("keyed", local=True)
        with pytest.raises(tamrm.Unauthenticated):
            nobody.session("keyed", local=True)
        with writer.session("keyed", 2, local=True) as s:
            s.step([0, 1], [1.0, 2.0], [True, True])
        stats = reader.get_task("keyed").stats
        assert (stats.pool_size, stats.episodes_completed, stats.steps_shaped) == (2, 2, 2)


def test_bad_arguments_fail_as_in_a_remote_session(
    remote_client: tamrm.Client, task_id: str
) -> None:
    remote_client.create_task(task_id, num_actions=3, pool_capacity=2)
    cases: list[Callable[[tamrm.Session], object]] = [
        lambda s: s.abandon([2]),
        lambda s: s.abandon([1, 1]),
        lambda s: s.abandon([-1]),
        lambda s: s.abandon([[0]]),
        lambda s: s.step([0, 3], [1.0, 1.0]),
        lambda s: s.step([0], [1.0], env_ids=[2]),
        lambda s: s.step([0, 1], [1.0, np.inf]),
        lambda s: s.step([0, 1], [1.0, 1.0], [True, False], episode_scores={1: 2.0}),
        lambda s: s.step([0, 1], [1.0, 1.0], values=[1.0, 2.0]),
    ]
    with (
        remote_client.session(task_id, 2, local=True) as local,
        remote_client.session(task_id, 2) as remote,
    ):
        for case in cases:
            errors = [outcome(lambda s=s, case=case: case(s)) for s in (local, remote)]
            assert errors[0] == errors[1]
            assert not local.closed and not remote.closed
        # Nothing was recorded by a failed call: both go on alike.
        for s in (local, remote):
            s.abandon([1])
        got, want = (s.step([0, 2], [1.0, 1.0], [True, True]) for s in (local, remote))
        assert got.steps.tolist() == want.steps.tolist() == [0, 0]


# -- the Python surface ----------------------------------------------------------------------


def test_local_is_a_property_kept_by_repr_pickling_and_restart(
    remote_client: tamrm.Client, task_id: str
) -> None:
    remote_client.create_task(task_id, num_actions=2, pool_capacity=2, min_pool_size=1)
    with remote_client.session(task_id, 2, local=True) as session:
        assert session.local is True
        assert repr(session) == f"<tamrm.Session task_id={task_id!r} num_envs=2 local open>"
        clone = pickle.loads(pickle.dumps(session))
        assert clone is not session
        assert (clone.task_id, clone.num_envs, clone.local) == (task_id, 2, True)
        assert not clone.closed
        assert clone._unpickled
        clone.step([0, 1], [1.0, 1.0], [True, False])
        clone.close()
        assert repr(clone).endswith("local closed>")
        assert open_streams(remote_client, task_id, 1) == 1  # the clone's ended
        session.step([1, 1], [1.0, 1.0])
        session.restart()  # episodes dropped, the session goes on
        assert session.episode_steps.tolist() == [0, 0]
        out = session.step([1, 0], [2.0, 2.0], [True, True])
        assert out.steps.tolist() == [0, 0] and out.pool_version == 3
    assert open_streams(remote_client, task_id, 0) == 0
    with remote_client.session(task_id) as remote:
        assert remote.local is False and " local " not in repr(remote)
        assert pickle.loads(pickle.dumps(remote)).local is False
    stats = remote_client.get_task(task_id).stats
    assert (stats.episodes_completed, stats.steps_shaped) == (3, 6)


def test_local_must_be_a_bool_and_is_for_a_client(
    remote_client: tamrm.Client, engine: tamrm.Engine, task_id: str
) -> None:
    remote_client.create_task(task_id, num_actions=2)
    with pytest.raises(TypeError, match="local must be a bool"):
        remote_client.session(task_id, local=1)  # type: ignore[arg-type]
    engine.create_task(task_id, num_actions=2)
    with pytest.raises(TypeError, match="in-process already"):
        engine.session(task_id, local=True)
    with engine.session(task_id, local=False) as s:
        assert s.local is False


def test_asyncio_local_session(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as client:
            await client.create_task(task_id, num_actions=2, pool_capacity=2, min_pool_size=1)
            session = client.session(task_id, 2, local=True)
            assert session.local and "local" in repr(session)
            async with session:
                out = await session.step([0, 1], [1.0, 1.0], [True, False])
                assert out.pool_version == 1 == session.pool_version
            with pytest.raises(TypeError, match="local must be a bool"):
                client.session(task_id, local="yes")  # type: ignore[arg-type]
            assert (await client.get_task(task_id)).stats.episodes_completed == 1

    asyncio.run(main())


# -- wrappers ----------------------------------------------------------------------------------

W = np.array([0.3, -0.2, 1.5, 0.7])


def _linear_value(obs: np.ndarray) -> np.ndarray:
    return np.asarray(obs, dtype=np.float64) @ W


def _cartpole_infos(session: tamrm.Session) -> list[tuple[Any, ...]]:
    env = tamrm.gym.ShapedReward(
        gym.make("CartPole-v1", max_episode_steps=25), session, value_fn=_linear_value
    )
    env.action_space.seed(1)
    out = []
    for episode in range(12):
        env.reset(seed=100 + episode)
        done = False
        while not done:
            _, reward, terminated, truncated, info = env.step(int(env.action_space.sample()))
            done = terminated or truncated
            out.append((float(reward).hex(), *(info[k] for k in tamrm.gym.INFO_KEYS)))
        if episode == 5:  # a reset in the middle of an episode abandons it
            env.reset(seed=7)
            for _ in range(3):
                env.step(0)
    env.close()
    return out


def test_gym_wrapper_with_a_local_session(remote_client: tamrm.Client) -> None:
    config = dict(num_actions=2, pool_capacity=4, k=3, start_step=3, min_pool_size=3)
    local_id, remote_id = _twin_tasks(remote_client, config)
    got = _cartpole_infos(remote_client.session(local_id, local=True))
    want = _cartpole_infos(remote_client.session(remote_id))
    assert got == want
    assert sum(info[5] for info in got) > 20  # knn_active
    assert_pools_equal(remote_client.get_pool(local_id), remote_client.get_pool(remote_id))
    assert open_streams(remote_client, local_id, 0) == 0  # the wrapper closed its session


def test_sb3_fast_path_with_a_local_session(remote_client: tamrm.Client) -> None:
    pytest.importorskip("stable_baselines3")
    import torch
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    import tamrm.sb3

    torch.set_num_threads(1)
    config = dict(num_actions=2, pool_capacity=4, k=3, start_step=2, min_pool_size=2, alpha=0.5)
    runs = []
    for task, local in zip(_twin_tasks(remote_client, config), (True, False), strict=True):
        venv = make_vec_env("CartPole-v1", n_envs=4, seed=0, env_kwargs={"max_episode_steps": 30})
        with remote_client.session(task, 4, local=local) as session:
            env = tamrm.sb3.ShapedVecEnv(venv, session)
            model = A2C("MlpPolicy", env, n_steps=5, seed=1)
            env.bind_model(model)
            model.learn(400)
            runs.append((env._vec_step.steps, env.take_stats(), model, task))
            env.close()
    (fast_local, stats_local, model_local, local_id), (fast_remote, stats, model, remote_id) = runs
    assert fast_local == fast_remote == 100  # every step through the native fast path
    assert stats_local == stats
    for p, q in zip(model_local.policy.parameters(), model.policy.parameters(), strict=True):
        assert torch.equal(p, q)
    assert_pools_equal(remote_client.get_pool(local_id), remote_client.get_pool(remote_id))
    assert_stats_equal(remote_client.get_task(local_id), remote_client.get_task(remote_id))


def test_a_local_session_pickled_into_subproc_workers(
    remote_client: tamrm.Client, task_id: str
) -> None:
    from stable_baselines3.common.vec_env import SubprocVecEnv

    client = remote_client
    client.create_task(task_id, num_actions=2, pool_capacity=8, min_pool_size=1)
    wrapper = tamrm.gym.ShapedReward(
        gym.make("CartPole-v1", max_episode_steps=10), client.session(task_id, local=True)
    )
    assert open_streams(client, task_id, 1) == 1
    venv = SubprocVecEnv([lambda: wrapper] * 2)
    try:
        venv.reset()
        for _ in range(25):
            venv.step_async(np.array([1, 0]))
            _, _, _, infos = venv.step_wait()
        # The parent's session plus a local session opened by each worker's copy.
        assert open_streams(client, task_id, 3) == 3
        assert all("knn_reward" in info for info in infos)
    finally:
        venv.close()
    assert open_streams(client, task_id, 1) == 1
    assert wrapper.session.local and not wrapper.session.closed
    wrapper.close()
    assert open_streams(client, task_id, 0) == 0
    stats = client.get_task(task_id).stats
    # Each worker ended its episodes (10 steps at most) and reported its 25 steps.
    assert stats.episodes_completed >= 4 and stats.steps_shaped == 50
    assert stats.pool_size > 0
