"""Clients, sessions and wrappers across processes."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AsyncVectorEnv
from stable_baselines3.common.vec_env import SubprocVecEnv
from streams import open_streams

import tamrm
import tamrm.gym
import tamrm.sb3


def test_client_pickles_by_address_and_settings(server: tamrm.LocalServer, task_id: str) -> None:
    with tamrm.Client(
        server.address, timeout=7.0, metadata=[("x-who", "me")], busy_poll_us=150
    ) as client:
        clone = pickle.loads(pickle.dumps(client))
        assert isinstance(clone, tamrm.Client)
        assert clone is not client
        assert (clone.target, clone.timeout) == (server.address, 7.0)
        assert clone._connection == client._connection  # every setting, busy_poll_us too
        assert clone._connection["busy_poll_us"] == 150
        clone.create_task(task_id, num_actions=2)
        assert client.get_task(task_id).task_id == task_id
        clone.close()
        assert copy.deepcopy(client) is client  # a handle: not duplicated by deepcopy


@pytest.fixture
def client(remote_client: tamrm.Client) -> tamrm.Client:
    # Pickling is the remote client's: an engine lives in one process.
    return remote_client


def test_engine_and_its_sessions_do_not_pickle(engine: tamrm.Engine, task_id: str) -> None:
    with pytest.raises(TypeError, match="tamrm serve"):
        pickle.dumps(engine)
    engine.create_task(task_id, num_actions=2)
    with engine.session(task_id, 2) as session:
        with pytest.raises(TypeError, match="tamrm serve"):
            pickle.dumps(session)


def test_session_pickles_as_a_new_session(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id, 3) as session:
        clone = pickle.loads(pickle.dumps(session))
        assert clone is not session
        assert (clone.task_id, clone.num_envs, clone.closed) == (task_id, 3, False)
        assert open_streams(client, task_id, 2) == 2
        clone.close()
    assert open_streams(client, task_id, 0) == 0


def shaped_cartpole(client: tamrm.Client, task_id: str) -> gym.Env:  # type: ignore[type-arg]
    return tamrm.gym.ShapedReward(gym.make("CartPole-v1"), client.session(task_id))


def run_vector(envs: gym.vector.VectorEnv, steps: int) -> dict:  # type: ignore[type-arg]
    envs.reset(seed=0)
    info: dict = {}  # type: ignore[type-arg]
    for _ in range(steps):
        _, _, _, _, info = envs.step(np.array([0, 1]))
    return info


def test_async_vector_env_factories_capture_the_client(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    # The factories capture the client: each worker reconnects and opens its own session.
    envs = AsyncVectorEnv([lambda: shaped_cartpole(client, task_id)] * 2, context="spawn")
    try:
        info = run_vector(envs, 5)
        assert open_streams(client, task_id, 2) == 2
        assert np.all(info["original_reward"] == 1.0)
        assert "knn_reward" in info
    finally:
        envs.close()
    # Each worker's wrapper owned its session and closed it.
    assert open_streams(client, task_id, 0) == 0


def test_subproc_vec_env_factory_captures_a_wrapper(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    wrapper = shaped_cartpole(client, task_id)  # built here, with a session of this process
    assert open_streams(client, task_id, 1) == 1
    venv = SubprocVecEnv([lambda: wrapper] * 2)
    try:
        venv.reset()
        for _ in range(3):
            venv.step_async(np.array([1, 0]))
            _, _, _, infos = venv.step_wait()
        assert [info["shaping_step"] for info in infos] == [2, 2]
        # The parent's session plus one opened by each worker's copy of the wrapper.
        assert open_streams(client, task_id, 3) == 3
    finally:
        venv.close()
    assert open_streams(client, task_id, 1) == 1
    assert not wrapper.session.closed
    wrapper.close()
    assert open_streams(client, task_id, 0) == 0
