"""``Session.abandon`` (SPEC v1.1 §12) against the real server, and the wrappers using it."""

from __future__ import annotations

import asyncio
import uuid
import warnings
from concurrent import futures

import grpc
import gymnasium as gym
import numpy as np
import pytest
from grpc_stubs import shaping_pb2_grpc as pb_grpc
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference import RefConfig, RefPool, RefStream

import tamrm
import tamrm.aio
import tamrm.gym
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb


def abandon_unsupported(err: tamrm.TamrmError) -> bool:
    """Whether ``err`` says that the server does not implement ``StepBatch.abandon``."""
    return err.code == tamrm.StatusCode.UNIMPLEMENTED and "abandon" in err.details


def stored(client: tamrm.Client, task_id: str) -> list[tuple[list[int], float]]:
    return [(t.actions.tolist(), t.score) for t in client.get_pool(task_id).trajectories]


def test_abandon_drops_the_episode(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=3, pool_capacity=5)
    with client.session(task_id, 3) as s:
        s.step([0, 1, 2], [1.0, 1.0, 1.0])
        s.step([0, 1, 2], [1.0, 1.0, 1.0])
        assert s.episodes_in_progress.tolist() == [True, True, True]
        s.abandon([2, 0])
        # At once on the client side: the next step of envs 0 and 2 starts a new episode.
        assert s.episodes_in_progress.tolist() == [False, True, False]
        assert s.episode_steps.tolist() == [0, 2, 0]
        res = s.step([1, 1, 1], [5.0, 1.0, 7.0], terminated=[True, True, True])
        assert res.steps.tolist() == [0, 2, 0]
    # The abandoned episodes were not offered to the pool; the new ones were.
    assert stored(client, task_id) == [([1], 5.0), ([1, 1, 1], 3.0), ([1], 7.0)]
    assert client.get_task(task_id).stats.episodes_completed == 3


def test_abandon_travels_with_the_next_batch(client: tamrm.Client, task_id: str) -> None:
    """Pending ids survive an empty step and a rejected (client-side) step; repeats merge."""
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        s.step([0, 0], [0.0, 0.0])
        s.step([0, 0], [0.0, 0.0])
        s.abandon([1])
        s.abandon(np.array([1], dtype=np.uint8))  # already pending: no duplicate sent
        assert len(s.step(np.zeros(0, np.int64), np.zeros(0), env_ids=np.zeros(0, np.int64))) == 0
        with pytest.raises(ValueError, match="actions"):
            s.step([0, 5], [0.0, 0.0])
        assert s.step([0, 0], [0.0, 0.0]).steps.tolist() == [2, 0]
        # Sent once: the following batch abandons nothing.
        assert s.step([0, 0], [0.0, 0.0]).steps.tolist() == [3, 1]
        # An env abandoned while not in a batch is confirmed at its next entry.
        s.abandon([0])
        assert s.step([0], [0.0], env_ids=[1]).steps.tolist() == [2]
        assert s.step([0, 0], [0.0, 0.0], env_ids=[0, 0]).steps.tolist() == [0, 1]
    assert client.get_task(task_id).stats.episodes_completed == 0


def test_abandon_validation(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 3) as s:
        s.step([0, 0, 0], [0.0, 0.0, 0.0])
        with pytest.raises(ValueError, match=r"abandon.*3.*num_envs=3"):
            s.abandon([0, 3])
        with pytest.raises(ValueError, match=r"abandon.*-1"):
            s.abandon([-1])
        with pytest.raises(ValueError, match=r"abandon.*env 1 is listed twice"):
            s.abandon([1, 2, 1])
        with pytest.raises(TypeError, match="abandon"):
            s.abandon([0.5])
        with pytest.raises(TypeError, match="abandon"):
            s.abandon([True])
        with pytest.raises(ValueError, match="abandon"):
            s.abandon([[0]])
        # Nothing was recorded: no episode dropped.
        assert s.episodes_in_progress.tolist() == [True, True, True]
        assert s.step([0, 0, 0], [0.0, 0.0, 0.0]).steps.tolist() == [1, 1, 1]
        s.abandon([])  # nothing to do
        s.abandon(2)  # one id
        assert s.step([0, 0, 0], [0.0, 0.0, 0.0]).steps.tolist() == [2, 2, 0]
    with pytest.raises(tamrm.SessionClosed):
        s.abandon([0])


def test_abandoned_episode_shaping_matches_reference(client: tamrm.Client, task_id: str) -> None:
    """After an abandon, kNN rewards use the new episode's prefix from t = 0."""
    client.create_task(task_id, num_actions=2, pool_capacity=2, min_pool_size=1, start_step=0)
    client.add_trajectory(task_id, [0, 0, 0, 0, 0], 2.0)
    client.add_trajectory(task_id, [1, 1, 1, 1, 1], 1.0)
    task = client.get_task(task_id)
    ref = RefPool(RefConfig.of(task.config))
    ref.sync(client.get_pool(task_id))
    stream = RefStream(ref, 2)
    plan = [([1, 0], None), ([1, 0], None), ([0, 0], [0]), ([0, 1], None), ([0, 1], [1, 0])]
    with client.session(task_id, 2) as s:
        for actions, abandon in plan:
            if abandon is not None:
                s.abandon(abandon)
                for env in abandon:
                    stream.abandon(env)
            res = s.step(actions, [0.0, 0.0])
            for env in range(2):
                want = stream.shape(env, actions[env], 0.0)
                assert res.steps[env] == want["step"]
                assert res.knn_rewards[env] == pytest.approx(want["knn_reward"], rel=1e-12)


def test_aio_abandon(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as c:
            await c.create_task(task_id, num_actions=2)
            async with c.session(task_id, 2) as s:
                await s.step([0, 1], [1.0, 1.0])
                s.abandon([0])
                assert s.episodes_in_progress.tolist() == [False, True]
                with pytest.raises(ValueError, match="twice"):
                    s.abandon([1, 1])
                res = await s.step([1, 1], [2.0, 2.0], terminated=[True, True])
                assert res.steps.tolist() == [0, 1]
            pool = await c.get_pool(task_id)
            assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [
                ([1], 2.0),
                ([1, 1], 3.0),
            ]

    asyncio.run(main())


# -- a server that predates abandon: the client notices instead of continuing ------------


class _OldShaping(pb_grpc.ShapingServicer):
    """A ``Shape`` stream that ignores ``StepBatch.abandon``, as servers before v1.1 do."""

    def Shape(self, request_iterator, context):  # type: ignore[no-untyped-def]
        steps: dict[int, int] = {}
        for req in request_iterator:
            if req.WhichOneof("kind") == "open":
                config = pb.TaskConfig(num_actions=2, pool_capacity=1, k=1, min_pool_size=1)
                yield pb.ShapeResponse(opened=pb.Task(task_id=req.open.task_id, config=config))
                continue
            batch = req.steps
            ids = list(batch.env_ids) or list(range(len(batch.rewards)))
            out = pb.ShapedBatch()
            for env, reward in zip(ids, batch.rewards, strict=True):
                out.steps.append(steps.get(env, 0))
                steps[env] = steps.get(env, 0) + 1
                out.rewards.append(reward)
                out.knn_rewards.append(0.0)
                out.potentials.append(0.0)
                out.knn_active.append(False)
            yield pb.ShapeResponse(shaped=out)


def test_server_ignoring_abandon_is_detected() -> None:
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    pb_grpc.add_ShapingServicer_to_server(_OldShaping(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        with tamrm.Client(f"127.0.0.1:{port}") as c, c.session("old", 2) as s:
            s.step([0, 0], [0.0, 0.0])
            s.abandon([1])
            with pytest.raises(tamrm.TamrmError) as err:
                s.step([0, 0], [0.0, 0.0])
            assert abandon_unsupported(err.value)
            assert "env 1" in err.value.details
            assert s.closed
    finally:
        server.stop(None)


# -- the wrappers abandon an episode reset by hand ---------------------------------------


def _cartpole_vector(num_envs: int) -> SyncVectorEnv:
    return SyncVectorEnv(
        [lambda: gym.make("CartPole-v1") for _ in range(num_envs)],
        autoreset_mode=AutoresetMode.DISABLED,
    )


def test_shaped_reward_reset_keeps_the_other_env(client: tamrm.Client, task_id: str) -> None:
    """Two single-env wrappers on one session: resetting one leaves the other's episode."""
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as session:
        a = tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session, env_id=0)
        b = tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session, env_id=1)
        a.reset(seed=0)
        b.reset(seed=1)
        for _ in range(3):
            a.step(0)
            b.step(1)
        a.reset(seed=2)  # mid-episode
        assert session.episodes_in_progress.tolist() == [False, True]
        assert a.step(0)[4]["shaping_step"] == 0
        assert b.step(1)[4]["shaping_step"] == 3
        a.close()
        b.close()
    assert client.get_task(task_id).stats.episodes_completed == 0


def test_vector_partial_reset_keeps_other_episodes(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 3) as session:
        envs = tamrm.gym.VectorShapedReward(_cartpole_vector(3), session)
        envs.reset(seed=0)
        envs.step(np.array([0, 1, 0]))
        envs.step(np.array([0, 1, 0]))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            envs.reset(options={"reset_mask": np.array([False, True, False])})
        assert session.episodes_in_progress.tolist() == [True, False, True]
        _, _, _, _, info = envs.step(np.array([1, 1, 1]))
        assert info["shaping_step"].tolist() == [2, 0, 2]
        envs.close()
    assert client.get_task(task_id).stats.episodes_completed == 0


def test_sb3_reset_mid_episode_abandons(client: tamrm.Client, task_id: str) -> None:
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_util import make_vec_env

    import tamrm.sb3

    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as session:
        env = tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2, seed=0), session)
        env.reset()
        for _ in range(3):
            env.step(np.array([0, 1]))
        env.reset()
        assert not session.episodes_in_progress.any()
        _, _, _, infos = env.step(np.array([0, 1]))
        assert [info["shaping_step"] for info in infos] == [0, 0]
        env.close()
    assert client.get_task(task_id).stats.episodes_completed == 0


# -- property: random abandons interleaved with steps equal the reference ---------------


@settings(max_examples=25, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    num_envs=st.integers(1, 3),
    ops=st.lists(
        st.tuples(
            st.lists(st.integers(0, 2), min_size=3, max_size=3),
            st.lists(st.booleans(), min_size=3, max_size=3),
            st.lists(st.booleans(), min_size=3, max_size=3),
        ),
        min_size=1,
        max_size=12,
    ),
)
def test_abandon_property(
    client: tamrm.Client, num_envs: int, ops: list[tuple[list[int], list[bool], list[bool]]]
) -> None:
    task_id = f"t/abandon-prop/{uuid.uuid4().hex}"
    task = client.create_task(
        task_id, num_actions=3, pool_capacity=2, min_pool_size=1, start_step=0
    )
    ref = RefPool(RefConfig.of(task.config))
    stream = RefStream(ref, num_envs)
    try:
        with client.session(task_id, num_envs) as s:
            for actions, abandon, ends in ops:
                ids = [e for e in range(num_envs) if abandon[e]]
                s.abandon(ids)
                for env in ids:
                    stream.abandon(env)
                acts = np.array(actions[:num_envs])
                done = np.array(ends[:num_envs])
                res = s.step(acts, np.ones(num_envs), terminated=done)
                for env in range(num_envs):
                    want = stream.shape(env, int(acts[env]), 1.0, bool(done[env]))
                    assert res.steps[env] == want["step"]
                    assert bool(res.knn_active[env]) == want["knn_active"]
                    assert res.rewards[env] == pytest.approx(want["reward"], rel=1e-12)
                assert res.pool_version == ref.version
        assert stored(client, task_id) == [
            (np.asarray(t.actions).tolist(), t.score) for t in ref.trajectories
        ]
    finally:
        client.delete_task(task_id)
