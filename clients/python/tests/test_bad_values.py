"""A bad number does not end a training run (the client's part)."""

from __future__ import annotations

import asyncio
import math

import gymnasium as gym
import numpy as np
import pytest

import tamrm
import tamrm.aio
import tamrm.gym


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        ({"rewards": [1.0, math.nan]}, "rewards[1] = nan is not finite"),
        ({"rewards": [math.inf, 1.0]}, "rewards[0] = inf is not finite"),
        ({"values": [0.0, 1e39], "next_values": [0.0, 0.0]}, "values[1] = 1e+39 does not fit"),
        ({"values": [0.0, 0.0], "next_values": [-math.inf, 0.0]}, "next_values[0] = -inf"),
        (
            {"q_values": [[0, 0], [0, math.nan]], "next_q_values": [[0, 0], [0, 0]]},
            "q_values[1, 1] = nan",
        ),
        ({"terminated": [True, False], "episode_scores": {0: math.nan}}, "episode_scores[0] = nan"),
        (
            {"terminated": [False, True], "episode_scores": [0.0, math.inf]},
            "episode_scores[1] = inf",
        ),
    ],
)
def test_bad_number_keeps_the_session(
    client: tamrm.Client,
    task_id: str,
    kwargs: dict,
    says: str,  # type: ignore[type-arg]
) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as s:
        s.step([0, 1], [1.0, 1.0])
        args = {"rewards": [1.0, 1.0], **kwargs}
        with pytest.raises(tamrm.InvalidArgument, match=r"the session is still usable") as err:
            s.step([0, 1], **args)
        assert says in err.value.details
        assert not s.closed
        # Nothing was sent: the episodes go on at step 1.
        assert s.step([0, 1], [1.0, 1.0]).steps.tolist() == [1, 1]
    assert client.get_task(task_id).stats.steps_shaped == 4


def test_bad_action_vector(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, action_dim=2)
    with client.session(task_id, 1) as s:
        with pytest.raises(tamrm.InvalidArgument, match=r"actions\[0, 1\] = 1e\+40 does not fit"):
            s.step([[0.0, 1e40]], [1.0])
        assert s.step([[0.0, 1.0]], [1.0]).steps.tolist() == [0]


def test_async_session_too(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> list[int]:
        async with tamrm.aio.Client(server.address) as c:
            await c.create_task(task_id, num_actions=2)
            async with c.session(task_id, 1) as s:
                await s.step([0], [1.0])
                with pytest.raises(tamrm.InvalidArgument, match="rewards"):
                    await s.step([0], [math.nan])
                return (await s.step([1], [1.0])).steps.tolist()

    assert asyncio.run(main()) == [1]


def test_a_diverging_critic_does_not_end_the_run(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    calls = {"n": 0}

    def critic(obs: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        return np.full(len(obs), math.nan if calls["n"] == 3 else 0.5)

    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session, critic)
        env.reset(seed=0)
        results = []
        for _ in range(5):
            try:
                results.append(env.step(0)[4]["shaping_step"])
            except tamrm.InvalidArgument as err:
                results.append(err.details.split(" ", 1)[0])
        assert results[2] == "values[0]"
        assert not session.closed
