"""A batch the server rejects ends nothing (SPEC §8, §9)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import tamrm
import tamrm.aio

CONFIG = dict(pool_capacity=50, k=2, start_step=1, min_pool_size=2, alpha=0.7, beta=0.3)


def make_tasks(client: tamrm.Client, task_id: str, discrete: bool) -> tuple[str, str]:
    ids = (task_id + "-a", task_id + "-b")
    for tid in ids:
        if discrete:
            client.create_task(tid, num_actions=3, **CONFIG)  # type: ignore[arg-type]
            demos = [np.array([0, 1, 2, 1, 0]), np.array([1, 1, 2, 0])]
        else:
            client.create_task(tid, action_dim=2, **CONFIG)  # type: ignore[arg-type]
            demos = [np.arange(10.0).reshape(5, 2) / 10, np.ones((4, 2)) / 3]
        for i, demo in enumerate(demos):
            client.add_trajectory(tid, demo, 3.0 + i)
    return ids


def script(discrete: bool, steps: int = 14) -> list[dict]:  # type: ignore[type-arg]
    rng = np.random.default_rng(7)
    out = []
    for t in range(steps):
        actions = rng.integers(0, 3, 2) if discrete else rng.normal(size=(2, 2)).round(3)
        out.append(
            {
                "actions": actions,
                "rewards": rng.normal(size=2).round(3),
                "terminated": np.array([t in (4, 11), t == 8]),
                "values": rng.normal(size=2).round(3),
                "next_values": rng.normal(size=2).round(3),
            }
        )
    return out


@pytest.mark.parametrize("discrete", [True, False], ids=["discrete", "continuous"])
def test_rejected_batch_then_the_run_goes_on(
    client: tamrm.Client, task_id: str, discrete: bool
) -> None:
    plain_task, hurt_task = make_tasks(client, task_id, discrete)
    with client.session(plain_task, 2) as plain, client.session(hurt_task, 2) as hurt:
        for t, step in enumerate(script(discrete)):
            if t in (3, 9):  # mid-episode on both envs, after episode ends on env 0 / 1
                with pytest.raises(tamrm.InvalidArgument, match="episode_scores"):
                    hurt.step(**step, episode_scores={1: 1.0} if t == 3 else {0: 1.0})
                assert not hurt.closed
            want, got = plain.step(**step), hurt.step(**step)
            assert got.steps.tolist() == want.steps.tolist()
            assert got.knn_active.tolist() == want.knn_active.tolist()
            np.testing.assert_allclose(got.knn_rewards, want.knn_rewards, rtol=1e-9)
            np.testing.assert_allclose(got.rewards, want.rewards, rtol=1e-9)
    a, b = client.get_pool(plain_task), client.get_pool(hurt_task)
    assert len(a) == len(b) == 5  # 2 demonstrations + 3 episode ends, each stored once
    for x, y in zip(a.trajectories, b.trajectories, strict=True):
        np.testing.assert_array_equal(x.actions, y.actions)
        assert x.score == pytest.approx(y.score)
    assert client.get_task(hurt_task).stats.open_streams == 0


def test_rejected_batch_async(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> tuple[list[int], int]:
        async with tamrm.aio.Client(server.address) as c:
            await c.create_task(task_id, num_actions=2)
            async with c.session(task_id, 1) as s:
                await s.step([0], [1.0])
                await s.step([1], [1.0])
                with pytest.raises(tamrm.InvalidArgument):
                    await s.step([0], [1.0], episode_scores={0: 2.0})
                steps = (await s.step([1], [1.0], terminated=[True])).steps.tolist()
            pool = await c.get_pool(task_id)
            return steps, len(pool.trajectories[0].actions)

    assert asyncio.run(main()) == ([2], 3)
