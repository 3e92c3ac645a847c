"""Closing a wrapper closes the session it owns."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import pytest
from stable_baselines3.common.env_util import make_vec_env
from streams import open_streams

import tamrm
import tamrm.gym
import tamrm.sb3


def reset(env: Any) -> None:
    if isinstance(env, tamrm.sb3.ShapedVecEnv):
        env.reset()
    else:
        env.reset(seed=0)


def single(session: tamrm.Session, **kw: Any) -> Any:
    return tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session, **kw)


def vector(session: tamrm.Session, **kw: Any) -> Any:
    return tamrm.gym.VectorShapedReward(gym.make_vec("CartPole-v1", num_envs=2), session, **kw)


def sb3(session: tamrm.Session, **kw: Any) -> Any:
    return tamrm.sb3.ShapedVecEnv(make_vec_env("CartPole-v1", n_envs=2), session, **kw)


WRAPPERS: list[tuple[Callable[..., Any], int]] = [(single, 1), (vector, 2), (sb3, 2)]


@pytest.mark.parametrize(("wrap", "n"), WRAPPERS, ids=["ShapedReward", "Vector", "ShapedVecEnv"])
def test_close_closes_the_session_handed_over(
    client: tamrm.Client, task_id: str, wrap: Callable[..., Any], n: int
) -> None:
    client.create_task(task_id, num_actions=2)
    env = wrap(client.session(task_id, n))
    reset(env)
    assert open_streams(client, task_id, 1) == 1
    env.close()
    assert env.session.closed
    assert open_streams(client, task_id, 0) == 0
    env.close()  # idempotent


@pytest.mark.parametrize(("wrap", "n"), WRAPPERS, ids=["ShapedReward", "Vector", "ShapedVecEnv"])
def test_close_leaves_a_session_owned_by_a_with_block(
    client: tamrm.Client, task_id: str, wrap: Callable[..., Any], n: int
) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, n) as session:
        env = wrap(session)
        reset(env)
        env.close()
        assert not session.closed
        assert open_streams(client, task_id, 1) == 1
        session.step([0] * n, [1.0] * n)  # still usable
    assert open_streams(client, task_id, 0) == 0


@pytest.mark.parametrize(("wrap", "n"), WRAPPERS, ids=["ShapedReward", "Vector", "ShapedVecEnv"])
def test_close_session_argument(
    client: tamrm.Client, task_id: str, wrap: Callable[..., Any], n: int
) -> None:
    client.create_task(task_id, num_actions=2)
    kept = client.session(task_id, n)
    wrap(kept, close_session=False).close()
    assert not kept.closed
    with client.session(task_id, n) as owned:
        wrap(owned, close_session=True).close()
        assert owned.closed
    assert open_streams(client, task_id, 1) == 1
    kept.close()
    assert open_streams(client, task_id, 0) == 0


def test_shared_session_survives_one_wrapper(client: tamrm.Client, task_id: str) -> None:
    # One session, two single-env wrappers (env_id 0 and 1): the with block owns it.
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 2) as session:
        a = single(session, env_id=0)
        b = single(session, env_id=1)
        a.reset(seed=0)
        b.reset(seed=1)
        a.close()
        b.step(1)
        b.close()
        assert not session.closed


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_wrapper_refused_at_construction_closes_quietly(
    client: tamrm.Client, task_id: str
) -> None:
    """A session that does not fit is a ValueError, and the half-built wrapper's cleanup
    (gymnasium's ``__del__``) raises nothing of its own."""
    import gc

    client.create_task(task_id, num_actions=2)
    envs = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync")
    with client.session(task_id, 3) as session, pytest.raises(ValueError):
        tamrm.gym.VectorShapedReward(envs, session)
    gc.collect()
    envs.close()
