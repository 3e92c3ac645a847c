"""Sessions against the real server, checked against a naive implementation of the SPEC."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest
from reference import RefConfig, RefPool, RefStream

import tamrm
import tamrm.aio


def assert_parts_consistent(result: tamrm.StepResult, rewards: np.ndarray, cfg: RefConfig) -> None:
    """R_meta == R + alpha * r + beta * F, from the returned parts."""
    expected = rewards + cfg.alpha * result.knn_rewards + cfg.beta * result.potentials
    np.testing.assert_allclose(result.rewards, expected, rtol=1e-12, atol=1e-12)


def assert_pool_equal(pool: tamrm.Pool, ref: RefPool) -> None:
    assert pool.pool_version == ref.version
    got = [(t.actions.tolist(), t.score) for t in pool.trajectories]
    want = [(np.asarray(t.actions).tolist(), t.score) for t in ref.trajectories]
    assert got == want


def run_against_reference(
    client: tamrm.Client,
    task_id: str,
    cfg: RefConfig,
    num_envs: int,
    num_steps: int,
    rng: np.random.Generator,
    *,
    replay: list[list[int]] | None = None,
    end_prob: float = 0.06,
    mode: str = "values",
) -> dict[str, int]:
    """Drive a session with random steps and check every entry against the reference."""
    ref = RefPool(cfg)
    ref.sync(client.get_pool(task_id))
    stream = RefStream(ref, num_envs)
    counts = {"active": 0, "nonzero_knn": 0, "terminated": 0, "truncated": 0, "scored": 0}
    with client.session(task_id, num_envs) as session:
        assert session.pool_version == ref.version
        for _ in range(num_steps):
            if cfg.num_actions:
                actions = rng.integers(0, cfg.num_actions, size=num_envs)
                if replay:
                    # Env 0 follows a stored trajectory (exact prefix matches, Z non-empty).
                    t0 = len(stream.episodes[0])
                    if t0 < len(replay[0]):
                        actions[0] = replay[0][t0]
            else:
                actions = rng.normal(size=(num_envs, cfg.action_dim))
            rewards = rng.normal(size=num_envs)
            ends = rng.random(num_envs) < end_prob
            terminated = ends & (rng.random(num_envs) < 0.5)
            truncated = ends & ~terminated
            scores = np.where(
                ends & (rng.random(num_envs) < 0.3), rng.normal(3, 2, num_envs), np.nan
            )
            kwargs: dict[str, np.ndarray] = {}
            values = next_values = [None] * num_envs
            if mode == "values":
                kwargs["values"] = rng.normal(size=num_envs)
                kwargs["next_values"] = rng.normal(size=num_envs)
                values, next_values = list(kwargs["values"]), list(kwargs["next_values"])
            elif mode == "q":
                kwargs["q_values"] = rng.normal(size=(num_envs, cfg.num_actions))
                kwargs["next_q_values"] = rng.normal(size=(num_envs, cfg.num_actions))
                # V = max_a Q, of the float32 values sent.
                values = list(kwargs["q_values"].astype(np.float32).max(axis=1))
                next_values = list(kwargs["next_q_values"].astype(np.float32).max(axis=1))
            result = session.step(
                actions, rewards, terminated, truncated, episode_scores=scores, **kwargs
            )
            assert len(result) == num_envs
            assert result.rewards.dtype == np.float64
            assert result.steps.dtype == np.int64
            assert result.knn_active.dtype == np.bool_
            assert result.env_ids.tolist() == list(range(num_envs))
            assert_parts_consistent(result, rewards, cfg)
            for env in range(num_envs):
                score = None if math.isnan(scores[env]) else float(scores[env])
                want = stream.shape(
                    env,
                    actions[env] if cfg.num_actions else np.asarray(actions[env], np.float32),
                    float(rewards[env]),
                    bool(terminated[env]),
                    bool(truncated[env]),
                    values[env],
                    next_values[env],
                    score,
                )
                assert result.steps[env] == want["step"]
                assert bool(result.knn_active[env]) == want["knn_active"], (env, want)
                assert result.knn_rewards[env] == pytest.approx(
                    want["knn_reward"], rel=1e-9, abs=1e-12
                )
                assert result.potentials[env] == pytest.approx(
                    want["potential"], rel=1e-6, abs=1e-6
                )
                assert result.rewards[env] == pytest.approx(want["reward"], rel=1e-6, abs=1e-6)
                counts["active"] += int(want["knn_active"])
                counts["nonzero_knn"] += int(want["knn_reward"] != 0.0)
                counts["scored"] += int(score is not None)
            counts["terminated"] += int(terminated.sum())
            counts["truncated"] += int(truncated.sum())
            assert result.pool_version == ref.version
            if ends.any():
                assert_pool_equal(client.get_pool(task_id), ref)
    return counts


def test_discrete_session_matches_reference(client: tamrm.Client, task_id: str) -> None:
    rng = np.random.default_rng(7)
    client.create_task(
        task_id,
        num_actions=3,
        pool_capacity=5,
        k=2,
        start_step=1,
        min_pool_size=3,
        alpha=0.7,
        beta=0.5,
        gamma=0.9,
        max_trajectory_len=40,
    )
    seeds = [rng.integers(0, 3, size=n).tolist() for n in (14, 18, 25)]
    for i, actions in enumerate(seeds):
        assert client.add_trajectory(task_id, actions, 10.0 + i).inserted
    seeded = client.get_task(task_id)
    cfg = RefConfig.of(seeded.config)
    counts = run_against_reference(client, task_id, cfg, 4, 160, rng, replay=seeds)
    # The run exercised what it claims to check.
    assert counts["active"] > 20 and counts["nonzero_knn"] > 20
    assert counts["terminated"] > 3 and counts["truncated"] > 3 and counts["scored"] > 1
    stats = client.get_task(task_id).stats
    assert stats.steps_shaped == 160 * 4
    ended = counts["terminated"] + counts["truncated"]
    assert stats.episodes_completed == seeded.stats.episodes_completed + ended


def test_discrete_session_q_values(client: tamrm.Client, task_id: str) -> None:
    rng = np.random.default_rng(11)
    client.create_task(task_id, num_actions=4, pool_capacity=3, start_step=0, gamma=0.95)
    for n in (6, 9, 7):
        client.add_trajectory(task_id, rng.integers(0, 4, size=n), float(n))
    cfg = RefConfig.of(client.get_task(task_id).config)
    counts = run_against_reference(client, task_id, cfg, 3, 60, rng, mode="q", end_prob=0.1)
    assert counts["terminated"] > 0 and counts["truncated"] > 0


def test_continuous_session_matches_reference(client: tamrm.Client, task_id: str) -> None:
    rng = np.random.default_rng(3)
    client.create_task(
        task_id, action_dim=2, pool_capacity=4, k=3, start_step=2, min_pool_size=2, beta=1.0
    )
    for n in (20, 24):
        client.add_trajectory(task_id, rng.normal(size=(n, 2)), float(rng.normal()))
    cfg = RefConfig.of(client.get_task(task_id).config)
    counts = run_against_reference(client, task_id, cfg, 3, 80, rng, end_prob=0.05)
    assert counts["nonzero_knn"] > 10
    pool = client.get_pool(task_id)
    assert all(t.actions.ndim == 2 and t.actions.shape[1] == 2 for t in pool.trajectories)


def test_potential_terminated_vs_truncated(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, gamma=0.5, beta=2.0)
    with client.session(task_id, 3) as s:
        res = s.step(
            [0, 1, 0],
            [1.0, 1.0, 1.0],
            [False, True, False],
            [False, False, True],
            values=[1.0, 1.0, 1.0],
            next_values=[4.0, 4.0, 4.0],
        )
    # Not done: 0.5*4-1 = 1; terminated: V(s') = 0 -> -1; truncated: the sent V(s') -> 1.
    np.testing.assert_array_equal(res.potentials, [1.0, -1.0, 1.0])
    np.testing.assert_array_equal(res.rewards, [3.0, -1.0, 3.0])
    np.testing.assert_array_equal(res.knn_rewards, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(res.steps, [0, 0, 0])


def test_no_values_means_no_potential(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        res = s.step(np.array([1, 0]), np.array([0.5, -2.0]))
    np.testing.assert_array_equal(res.potentials, [0.0, 0.0])
    np.testing.assert_array_equal(res.rewards, [0.5, -2.0])


def test_episode_steps_and_pool_contents(client: tamrm.Client, task_id: str) -> None:
    """Episodes of different lengths end at different steps; the pool stores them."""
    client.create_task(task_id, num_actions=3, pool_capacity=10, max_trajectory_len=4)
    lengths = [3, 5, 2]
    actions_taken: list[list[int]] = [[], [], []]
    rewards_sum = [0.0, 0.0, 0.0]
    with client.session(task_id, 3) as s:
        for t in range(5):
            active = [e for e in range(3) if t < lengths[e]]
            acts = np.array([(e + t) % 3 for e in active], dtype=np.int64)
            rews = np.array([0.5 * (e + 1) for e in active])
            done = np.array([t == lengths[e] - 1 for e in active])
            res = s.step(acts, rews, terminated=done, env_ids=np.array(active))
            assert res.env_ids.tolist() == active
            assert res.steps.tolist() == [t] * len(active)
            for e, a, r in zip(active, acts, rews, strict=True):
                actions_taken[e].append(int(a))
                rewards_sum[e] += float(r)
            assert s.episodes_in_progress.tolist() == [t < lengths[e] - 1 for e in range(3)]
    pool = client.get_pool(task_id)
    # Stored in order of episode end: env 2 (t=1), env 0 (t=2), env 1 (t=4, truncated to 4).
    got = [(t.actions.tolist(), t.score) for t in pool.trajectories]
    assert got == [
        (actions_taken[2], rewards_sum[2]),
        (actions_taken[0], rewards_sum[0]),
        (actions_taken[1][:4], rewards_sum[1]),
    ]


def test_same_env_twice_in_one_batch(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, pool_capacity=1, min_pool_size=1, start_step=0)
    with client.session(task_id, 2) as s:
        res = s.step([1, 0, 1], [1.0, 2.0, 3.0], [True, False, False], env_ids=[0, 0, 1])
        assert res.steps.tolist() == [0, 0, 0]
        # Entry 0 ended env 0's episode and was stored before entry 1 was processed.
        assert res.knn_active.tolist() == [False, True, True]
        assert res.pool_version == s.task.stats.pool_version + 1
        # Env 0 just started a new episode with action 0 != stored [1]: dis = 2, P = 1,
        # single trajectory -> x = 1, r = e^1 - e^0.5.
        assert res.knn_rewards[1] == pytest.approx(math.exp(1) - math.exp(0.5))
        assert res.knn_rewards[2] == pytest.approx(math.exp(1) - math.exp(0.5))


def test_empty_step_sends_nothing(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        res = s.step(np.zeros(0, np.int64), np.zeros(0), env_ids=np.zeros(0, np.int64))
        assert len(res) == 0
    assert client.get_task(task_id).stats.steps_shaped == 0


def test_session_validation_sends_nothing(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        s.step([0, 1], [1.0, 1.0])
        with pytest.raises(ValueError, match="actions"):
            s.step([0, 2], [1.0, 1.0])
        with pytest.raises(ValueError, match="rewards"):
            s.step([0, 1], [1.0, 1.0, 1.0])
        with pytest.raises(TypeError, match="next_values"):
            s.step([0, 1], [1.0, 1.0], values=[0.0, 0.0])
        with pytest.raises(ValueError, match="env_ids"):
            s.step([0], [1.0], env_ids=[2])
        assert not s.closed
        res = s.step([0, 1], [1.0, 1.0])
        assert res.steps.tolist() == [1, 1]
    assert client.get_task(task_id).stats.steps_shaped == 4


def test_server_rejection_surfaces_on_the_step(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, pool_capacity=2)
    before = client.get_task(task_id).stats
    s = client.session(task_id, 2)
    s.step([0, 1], [1.0, 1.0])
    # A non-finite number is caught before sending: the session stays usable.
    with pytest.raises(tamrm.InvalidArgument) as err:
        s.step([0, 1], [math.nan, 1.0])
    assert "reward" in err.value.details
    assert not s.closed
    # A rejection by the server (a score on an entry that does not end its episode) changes
    # nothing (SPEC §8): the session goes on on a new stream, its episodes resumed (§9).
    with pytest.raises(tamrm.InvalidArgument) as err:
        s.step([0, 1], [1.0, 1.0], episode_scores={0: 1.0})
    assert "episode_scores" in err.value.details
    assert not s.closed
    assert s.step([0, 1], [1.0, 1.0]).steps.tolist() == [1, 1]
    s.close()
    # A score on an entry that does not end an episode: the whole batch is rejected,
    # including env 0's episode end.
    with client.session(task_id, 2) as s2:
        with pytest.raises(tamrm.InvalidArgument) as err:
            s2.step([0, 1], [1.0, 1.0], terminated=[True, False], episode_scores={1: 5.0})
        assert "episode_scores" in err.value.details
    after = client.get_task(task_id).stats
    assert after.pool_version == before.pool_version
    assert after.pool_size == 0
    assert after.episodes_completed == 0


def test_non_finite_values_rejected(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 1) as s, pytest.raises(tamrm.InvalidArgument) as err:
        s.step([0], [1.0], values=[math.inf], next_values=[0.0])
    assert "values" in err.value.details


def test_restart_discards_unfinished_episodes(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        s.step([0, 1], [1.0, 1.0])
        s.step([0, 1], [1.0, 1.0])
        assert s.episodes_in_progress.tolist() == [True, True]
        s.restart()
        assert not s.closed and s.episodes_in_progress.tolist() == [False, False]
        res = s.step([1, 1], [2.0, 2.0], terminated=[True, False])
        assert res.steps.tolist() == [0, 0]
    pool = client.get_pool(task_id)
    assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [([1], 2.0)]
    assert client.get_task(task_id).stats.episodes_completed == 1


def test_episodes_ended_after_a_restart_are_stored(client: tamrm.Client, task_id: str) -> None:
    # SPEC §9: after a restart every env starts a new episode. The session keeps its
    # client id, so the server must number them after the ends it committed, not from 0
    # again (where they would be taken for re-sends of the first ones and dropped).
    client.create_task(task_id, num_actions=2, pool_capacity=10)
    with client.session(task_id, 2) as s:
        for score in (1.0, 2.0):
            s.step([0, 1], [score, score], terminated=[True, True])
        assert client.get_task(task_id).stats.pool_size == 4
        for round_ in range(2):
            s.restart()
            s.step([1, 0], [5.0 + round_, 6.0 + round_], terminated=[True, True])
    stats = client.get_task(task_id).stats
    assert (stats.pool_size, stats.episodes_completed) == (8, 8)
    scores = sorted(t.score for t in client.get_pool(task_id).trajectories)
    assert scores == [1.0, 1.0, 2.0, 2.0, 5.0, 6.0, 6.0, 7.0]


def _wait_for(predicate, timeout: float = 5.0) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return bool(predicate())


def test_open_streams_and_close(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    s1 = client.session(task_id, 1)
    s2 = client.session(task_id, 4)
    assert s2.task.stats.open_streams >= 1
    assert client.get_task(task_id).stats.open_streams == 2
    s1.step([1], [1.0])
    s1.close()
    s1.close()  # idempotent
    assert _wait_for(lambda: client.get_task(task_id).stats.open_streams == 1)
    with pytest.raises(tamrm.SessionClosed):
        s1.step([1], [1.0])
    s2.close()
    assert _wait_for(lambda: client.get_task(task_id).stats.open_streams == 0)
    # s1's unfinished episode was discarded.
    assert client.get_task(task_id).stats.episodes_completed == 0


def test_two_sessions_share_the_pool(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, pool_capacity=1, min_pool_size=1, start_step=0)
    with client.session(task_id, 1) as a, client.session(task_id, 1) as b:
        assert not b.step([0], [1.0]).knn_active[0]
        ra = a.step([1], [1.0], terminated=[True])
        assert not ra.knn_active[0]
        rb = b.step([0], [1.0])
        assert rb.pool_version == ra.pool_version
        # b's episode is [0, 0], the stored one [1]: t = 1 >= L_min = 1 -> inactive.
        assert not rb.knn_active[0]
        rb2 = b.step([0], [1.0], terminated=[True])
        # b's episode [0, 0, 0] scores 3 > 1: it replaces a's.
        assert rb2.pool_version == ra.pool_version + 1
    pool = client.get_pool(task_id)
    assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [([0, 0, 0], 3.0)]


def test_reset_pool_during_session(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2, pool_capacity=1, min_pool_size=1, start_step=0)
    client.add_trajectory(task_id, [0, 0, 0], 1.0)
    with client.session(task_id, 1) as s:
        assert s.step([0], [0.0]).knn_active[0]
        version = client.reset_pool(task_id).stats.pool_version
        res = s.step([0], [0.0])
        assert not res.knn_active[0]
        assert res.pool_version == version


def test_delete_task_during_session(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    s = client.session(task_id, 1)
    s.step([0], [0.0])
    client.delete_task(task_id)
    with pytest.raises(tamrm.TaskNotFound):
        s.step([0], [0.0])
    assert s.closed
    s.close()


def test_session_argument_checks(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with pytest.raises(ValueError, match="num_envs"):
        client.session(task_id, 0)
    with pytest.raises(TypeError, match="num_envs"):
        client.session(task_id, 1.5)  # type: ignore[arg-type]
    with pytest.raises(tamrm.InvalidArgument):
        client.session("bad id!", 1)


def test_limits_resource_exhausted(server_binary: str) -> None:
    args = ["--max-tasks", "2", "--max-envs-per-stream", "4", "--max-batch-entries", "6"]
    args += ["--max-pool-capacity", "50"]
    with tamrm.local_server(binary=server_binary, args=args) as srv, srv.client() as c:
        c.create_task("a", num_actions=2)
        with pytest.raises(tamrm.ResourceExhausted) as err:
            c.create_task("b", num_actions=2, pool_capacity=51)
        assert "pool_capacity" in err.value.details
        c.create_task("b", num_actions=2)
        with pytest.raises(tamrm.ResourceExhausted) as err:
            c.create_task("c", num_actions=2)
        with pytest.raises(tamrm.ResourceExhausted) as err:
            c.session("a", 5)
        assert "num_envs" in err.value.details
        with c.session("a", 4) as s:
            s.step([0] * 6, [0.0] * 6, env_ids=[0, 1, 2, 3, 0, 1])
            with pytest.raises(tamrm.ResourceExhausted):
                s.step([0] * 7, [0.0] * 7, env_ids=[0, 1, 2, 3, 0, 1, 2])


def test_aio_client_and_session(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as c:
            task = await c.create_task(task_id, num_actions=2, pool_capacity=2, start_step=0)
            assert task.config.min_pool_size == 2
            assert (await c.get_task(task_id)).task_id == task_id
            assert task_id in [t.task_id for t in await c.list_tasks()]
            assert (await c.add_trajectory(task_id, [0, 1, 1], 2.0)).inserted
            assert (await c.add_trajectory(task_id, [0, 0, 1], 1.0)).inserted
            pool = await c.get_pool(task_id)
            assert [t.actions.tolist() for t in pool.trajectories] == [[0, 1, 1], [0, 0, 1]]
            ref = RefPool(RefConfig.of(task.config))
            ref.sync(pool)
            stream = RefStream(ref, 2)
            async with c.session(task_id, 2) as s:
                for t in range(4):
                    acts = np.array([t % 2, 0])
                    rews = np.array([1.0, 0.5])
                    done = np.array([t == 3, False])
                    res = await s.step(acts, rews, done, values=[0.5, 1.0], next_values=[1.0, 2.0])
                    for e in range(2):
                        want = stream.shape(
                            e,
                            int(acts[e]),
                            float(rews[e]),
                            bool(done[e]),
                            False,
                            0.5 if e == 0 else 1.0,
                            1.0 if e == 0 else 2.0,
                        )
                        assert res.knn_active[e] == want["knn_active"]
                        assert res.knn_rewards[e] == pytest.approx(want["knn_reward"])
                        assert res.rewards[e] == pytest.approx(want["reward"], rel=1e-6)
                with pytest.raises(tamrm.InvalidArgument):  # rejected by the server
                    await s.step([0, 0], [0.0, 0.0], episode_scores={1: 5.0})
                # Nothing changed (SPEC §8): the episodes go on, on a resumed stream (§9).
                assert not s.closed
                assert (await s.step([0, 0], [0.0, 0.0])).steps.tolist() == [0, 4]
            assert_pool_equal(await c.get_pool(task_id), ref)
            s2 = await c.session(task_id, 1)
            await s2.step([1], [1.0])
            await s2.restart()
            assert (await s2.step([1], [1.0])).steps.tolist() == [0]
            await s2.close()
            assert (await c.reset_pool(task_id)).stats.pool_size == 0
            await c.delete_task(task_id)
            with pytest.raises(tamrm.TaskNotFound):
                await c.get_task(task_id)
            with pytest.raises(tamrm.TaskNotFound):
                await c.session(task_id, 1)

    asyncio.run(main())


def test_unclosed_session_is_released(client: tamrm.Client, task_id: str) -> None:
    """A session dropped without close(): stream ended, gRPC's request thread gone."""
    import gc
    import threading

    client.create_task(task_id, num_actions=2)
    gc.collect()
    threads = threading.active_count()
    for _ in range(3):
        s = client.session(task_id, 1)
        s.step([0], [1.0])
        del s
    gc.collect()
    assert _wait_for(lambda: client.get_task(task_id).stats.open_streams == 0)
    assert _wait_for(lambda: threading.active_count() <= threads)


def test_aio_delete_task_during_session(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as c:
            await c.create_task(task_id, num_actions=3)
            session = await c.session(task_id, 2)
            with pytest.raises(ValueError, match="actions"):
                await session.step([0, 3], [0.0, 0.0])  # client-side: nothing sent
            res = await session.step([0, 2], [0.0, 0.0])
            assert res.steps.tolist() == [0, 0]
            assert (await c.get_task(task_id)).stats.open_streams == 1
            await c.delete_task(task_id)
            with pytest.raises(tamrm.TaskNotFound):
                await session.step([0, 1], [0.0, 0.0])
            assert session.closed
            await session.close()

    asyncio.run(main())
