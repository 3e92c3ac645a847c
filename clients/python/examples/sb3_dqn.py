#!/usr/bin/env python3
"""SB3 DQN on CartPole-v1 shaped by tamrm with the model's own Q-values, then evaluated.

``bind_model`` sends DQN's Q-values (``policy.q_net``) and the server takes
V(s) = max_a Q(s, a) for the potential term. The evaluation runs the trained model on a
plain, unshaped env (``evaluate_policy`` on a fresh ``make_vec_env``), not through the
``ShapedVecEnv``: evaluation episodes then neither feed the shared pool nor count as
training steps, and the returns are the environment's own.

    python clients/python/examples/sb3_dqn.py                 # a local server
    python clients/python/examples/sb3_dqn.py --quick         # smoke test
    python clients/python/examples/sb3_dqn.py --server 127.0.0.1:50051
"""

from __future__ import annotations

import argparse
import contextlib
import uuid
from collections.abc import Iterator

import torch
from stable_baselines3 import DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

import tamrm
import tamrm.sb3


@contextlib.contextmanager
def connect(server: str | None) -> Iterator[tamrm.Client]:
    if server is not None:
        with tamrm.Client(server) as client:
            client.list_tasks()  # fail now, not after training
            yield client
        return
    with tamrm.local_server(in_memory=True) as local, tamrm.Client(local.address) as client:
        yield client


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timesteps", type=int, default=50_000)
    parser.add_argument("--quick", action="store_true", help="smoke test: 2,000 timesteps")
    ns = parser.parse_args()
    timesteps = 2_000 if ns.quick else ns.timesteps
    torch.set_num_threads(1)

    with connect(ns.server) as client:
        task_id = f"examples/sb3-dqn/{uuid.uuid4().hex[:8]}"
        client.create_task(task_id, num_actions=2)
        venv = make_vec_env("CartPole-v1", n_envs=4, seed=ns.seed)
        with client.session(task_id, venv.num_envs) as session:
            env = tamrm.sb3.ShapedVecEnv(venv, session)
            model = DQN(
                "MlpPolicy", env, learning_starts=500, seed=ns.seed, device="cpu", verbose=1
            )
            env.bind_model(model)  # Q-values from model.q_net
            model.learn(timesteps)
            env.close()
        trained = client.get_task(task_id).stats

        # Q-values of a start state, as the potential term saw them.
        obs = make_vec_env("CartPole-v1", n_envs=1, seed=ns.seed).reset()
        with torch.no_grad():
            q = model.q_net(model.policy.obs_to_tensor(obs)[0]).numpy()[0]
        q_text = ", ".join(f"{v:.3f}" for v in q)
        print(f"Q(s0, .) = [{q_text}]  (V(s0) = max = {q.max():.3f})")

        # Evaluate on the unshaped env: no session, nothing reaches the pool.
        mean, std = evaluate_policy(
            model, make_vec_env("CartPole-v1", n_envs=1, seed=ns.seed + 1), n_eval_episodes=10
        )
        after = client.get_task(task_id).stats
        assert after.pool_version == trained.pool_version, "evaluation fed the pool"
        print(
            f"trained {model.num_timesteps} steps ({trained.episodes_completed} episodes, "
            f"pool {trained.pool_size}); evaluation return {mean:.1f} +- {std:.1f} "
            "(unshaped, pool untouched)"
        )


if __name__ == "__main__":
    main()
