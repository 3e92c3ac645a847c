#!/usr/bin/env python3
"""CleanRL-style single-file PPO on CartPole-v1 with tamrm shaping.

The PPO loop is CleanRL's ``ppo.py`` in miniature (GAE, clipped objective, value loss,
entropy bonus); the only tamrm lines are the task, the session and the
``VectorShapedReward`` wrapper, whose ``value_fn`` is the agent's own critic. Per update it
logs the environment return R, the shaping parts alpha * r(t) and beta * F, and the pool
size: to TensorBoard (``runs/``) when ``tensorboard`` is installed, else to stdout.

    python clients/python/examples/cleanrl_ppo.py                 # a local server
    python clients/python/examples/cleanrl_ppo.py --quick         # smoke test
    python clients/python/examples/cleanrl_ppo.py --server 127.0.0.1:50051

Episode returns are the environment's own: ``RecordEpisodeStatistics`` sits inside each
sub-environment, below the shaping wrapper.
"""

from __future__ import annotations

import argparse
import contextlib
import time
import uuid
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical

import tamrm
import tamrm.gym


class Agent(nn.Module):
    def __init__(self, obs_dim: int, n_actions: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(nn.Linear(obs_dim, 64), nn.Tanh(), nn.Linear(64, 1))
        self.actor = nn.Sequential(nn.Linear(obs_dim, 64), nn.Tanh(), nn.Linear(64, n_actions))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def act(
        self, x: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        dist = Categorical(logits=self.actor(x))
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action), dist.entropy(), self.value(x)


class Logger:
    """TensorBoard's SummaryWriter when available, else lines on stdout."""

    def __init__(self, run: str) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self.writer: Any = None
            print("(tensorboard not installed: logging to stdout)")
        else:
            self.writer = SummaryWriter(f"runs/{run}")

    def log(self, step: int, **scalars: float) -> None:
        if self.writer is not None:
            for key, value in scalars.items():
                self.writer.add_scalar(key, value, step)
        else:
            print(f"step {step:>7}  " + "  ".join(f"{k}={v:.3f}" for k, v in scalars.items()))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


@contextlib.contextmanager
def connect(server: str | None) -> Iterator[tamrm.Client]:
    if server is not None:
        with tamrm.Client(server) as client:
            client.list_tasks()  # fail now, not after a rollout
            yield client
        return
    with tamrm.local_server(in_memory=True) as local, tamrm.Client(local.address) as client:
        yield client


def train(client: tamrm.Client, ns: argparse.Namespace) -> None:
    torch.manual_seed(ns.seed)
    envs = gym.vector.SyncVectorEnv(
        [lambda: gym.wrappers.RecordEpisodeStatistics(gym.make("CartPole-v1"))] * ns.num_envs,
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,  # CleanRL's classic semantics
    )
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    agent = Agent(obs_dim, int(envs.single_action_space.n))  # type: ignore[attr-defined]
    optimizer = torch.optim.Adam(agent.parameters(), lr=2.5e-4, eps=1e-5)

    def critic(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return agent.value(torch.as_tensor(obs, dtype=torch.float32)).numpy()

    task_id = f"examples/cleanrl-ppo/{uuid.uuid4().hex[:8]}"
    config = client.create_task(task_id, num_actions=2).config
    logger = Logger(task_id.replace("/", "-"))
    n, steps = ns.num_envs, ns.num_steps
    obs_buf = torch.zeros((steps, n, obs_dim))
    act_buf = torch.zeros((steps, n), dtype=torch.long)
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros((steps, n)) for _ in range(4))

    with client.session(task_id, n) as session:
        env = tamrm.gym.VectorShapedReward(envs, session, value_fn=critic)
        obs, _ = env.reset(seed=ns.seed)
        next_obs = torch.as_tensor(obs, dtype=torch.float32)
        next_done = torch.zeros(n)
        returns: list[float] = []
        global_step, start = 0, time.time()
        for _ in range(ns.updates):
            parts = np.zeros(3)  # R, alpha * r(t), beta * F summed over the rollout
            for t in range(steps):
                global_step += n
                obs_buf[t], done_buf[t] = next_obs, next_done
                with torch.no_grad():
                    action, logp, _, value = agent.act(next_obs)
                act_buf[t], logp_buf[t], val_buf[t] = action, logp, value
                obs, reward, term, trunc, info = env.step(action.numpy())
                rew_buf[t] = torch.as_tensor(reward, dtype=torch.float32)
                next_obs = torch.as_tensor(obs, dtype=torch.float32)
                next_done = torch.as_tensor(term | trunc, dtype=torch.float32)
                parts += [
                    info["original_reward"].sum(),
                    config.alpha * info["knn_reward"].sum(),
                    config.beta * info["potential"].sum(),
                ]
                final = info.get("final_info", {})
                if "episode" in final:
                    returns += final["episode"]["r"][final["_episode"]].tolist()

            with torch.no_grad():  # GAE
                next_value = agent.value(next_obs)
                adv = torch.zeros_like(rew_buf)
                last = torch.zeros(n)
                for t in reversed(range(steps)):
                    nonterminal = 1.0 - (next_done if t == steps - 1 else done_buf[t + 1])
                    v_next = next_value if t == steps - 1 else val_buf[t + 1]
                    delta = rew_buf[t] + 0.99 * v_next * nonterminal - val_buf[t]
                    adv[t] = last = delta + 0.99 * 0.95 * nonterminal * last
                ret = adv + val_buf

            b_obs, b_act = obs_buf.reshape(-1, obs_dim), act_buf.reshape(-1)
            b_logp, b_adv, b_ret = logp_buf.reshape(-1), adv.reshape(-1), ret.reshape(-1)
            for _ in range(4):
                for idx in torch.randperm(n * steps).split(n * steps // 4):
                    _, logp, entropy, value = agent.act(b_obs[idx], b_act[idx])
                    ratio = (logp - b_logp[idx]).exp()
                    a = (b_adv[idx] - b_adv[idx].mean()) / (b_adv[idx].std() + 1e-8)
                    pg_loss = torch.max(-a * ratio, -a * ratio.clamp(0.8, 1.2)).mean()
                    v_loss = 0.5 * ((value - b_ret[idx]) ** 2).mean()
                    loss = pg_loss + 0.5 * v_loss - 0.01 * entropy.mean()
                    optimizer.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                    optimizer.step()

            stats = client.get_task(task_id).stats
            logger.log(
                global_step,
                **{
                    "charts/episodic_return": float(np.mean(returns[-20:])) if returns else 0.0,
                    "shaping/R": parts[0] / (n * steps),
                    "shaping/alpha_r": parts[1] / (n * steps),
                    "shaping/beta_F": parts[2] / (n * steps),
                    "shaping/pool_size": float(stats.pool_size),
                    "charts/SPS": global_step / (time.time() - start),
                },
            )
        env.close()
    logger.close()
    print(f"{len(returns)} episodes, last-20 mean return {np.mean(returns[-20:]):.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--num-envs", type=int, default=4)
    parser.add_argument("--num-steps", type=int, default=128)
    parser.add_argument("--updates", type=int, default=150)
    parser.add_argument("--quick", action="store_true", help="smoke test: 3 updates")
    ns = parser.parse_args()
    if ns.quick:
        ns.updates, ns.num_steps = 3, 32
    torch.set_num_threads(1)
    with connect(ns.server) as client:
        train(client, ns)


if __name__ == "__main__":
    main()
