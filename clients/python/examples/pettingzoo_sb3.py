#!/usr/bin/env python3
"""Parameter-sharing PPO (Stable-Baselines3) on PettingZoo's MPE simple_spread, shaped by tamrm.

Three agents learn one shared policy: SuperSuit turns the parallel env into a vector env
with one entry per agent (``pettingzoo_env_to_vec_env_v1``) and stacks copies of it
(``concat_vec_envs_v1``), in this process or in worker processes. The shaping wrapper
sits on the PettingZoo env itself, first, so each agent's episode is its own:

    env = tamrm.pettingzoo.ShapedParallel(simple_spread_v3.parallel_env(), client, task)
    # (an env whose agents die: supersuit.black_death_v3(env) here, after the shaping)
    venv = supersuit.pettingzoo_env_to_vec_env_v1(env)
    venv = supersuit.concat_vec_envs_v1(venv, 4, num_cpus=2, base_class="stable_baselines3")

    python clients/python/examples/pettingzoo_sb3.py                        # one shared pool
    python clients/python/examples/pettingzoo_sb3.py --layout per-agent     # a pool per agent
    python clients/python/examples/pettingzoo_sb3.py --quick                # smoke test
    python clients/python/examples/pettingzoo_sb3.py --server 127.0.0.1:50051 --num-cpus 2

Without ``--server`` a ``tamrm`` binary is started with :func:`tamrm.local_server`;
``--engine`` shapes in this process instead (then SuperSuit's copies stay in this
process: ``--num-cpus 0``). Needs ``pip install 'tamrm[pettingzoo,sb3]' mpe2``.
"""

from __future__ import annotations

import argparse
import contextlib
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import supersuit as ss
import torch
from mpe2 import simple_spread_v3
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import set_random_seed

import tamrm
import tamrm.pettingzoo

N_AGENTS = 3
MAX_CYCLES = 25


class EnvReturns(BaseCallback):
    """The environment's own (unshaped) return of every finished agent-episode."""

    def __init__(self) -> None:
        super().__init__()
        self.returns: list[float] = []
        self._sums: np.ndarray | None = None

    def _on_step(self) -> bool:
        infos: list[dict[str, Any]] = self.locals["infos"]
        dones: np.ndarray = self.locals["dones"]
        if self._sums is None:
            self._sums = np.zeros(len(infos))
        self._sums += [info.get("original_reward", 0.0) for info in infos]
        for i in np.flatnonzero(dones):
            self.returns.append(float(self._sums[i]))
            self._sums[i] = 0.0
        return True


@contextlib.contextmanager
def shaping_api(server: str | None, engine: bool) -> Iterator[tamrm.Engine | tamrm.Client]:
    """An in-process engine, a client of ``server``, or a client of a local server."""
    if engine:
        with tamrm.Engine() as api:
            yield api
    elif server is not None:
        with tamrm.Client(server) as client:
            client.list_tasks()  # fail now, not in SuperSuit's workers
            yield client
    else:
        with tamrm.local_server(in_memory=True) as local, tamrm.Client(local.address) as client:
            yield client


def task_map(base: str, layout: str) -> str | Callable[[str], str]:
    """One task for every agent, or a task per agent (``base/agent_0``, ...)."""
    if layout == "shared":
        return base
    return lambda agent: f"{base}/{agent}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--engine", action="store_true", help="shape in-process (tamrm.Engine)")
    parser.add_argument("--layout", choices=["shared", "per-agent"], default="shared")
    parser.add_argument("--copies", type=int, default=4, help="env copies SuperSuit stacks")
    parser.add_argument("--num-cpus", type=int, default=0, help="SuperSuit worker processes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timesteps", type=int, default=300_000, help="agent-steps")
    parser.add_argument("--quick", action="store_true", help="smoke test: 3 PPO updates")
    ns = parser.parse_args()
    if ns.engine and ns.num_cpus:
        parser.error("--engine shapes in this process: use --num-cpus 0 (or a server)")
    copies = 2 if ns.quick else ns.copies
    n_steps = 64 if ns.quick else 256
    timesteps = 3 * n_steps * copies * N_AGENTS if ns.quick else ns.timesteps
    torch.set_num_threads(1)

    with shaping_api(ns.server, ns.engine) as api:
        base = f"examples/pettingzoo-sb3/{uuid.uuid4().hex[:8]}"
        task = task_map(base, ns.layout)
        env = simple_spread_v3.parallel_env(N=N_AGENTS, max_cycles=MAX_CYCLES)
        task_ids = sorted({task if isinstance(task, str) else task(a) for a in env.possible_agents})
        for task_id in task_ids:
            api.create_task(task_id, num_actions=5)  # simple_spread: Discrete(5) per agent

        shaped = tamrm.pettingzoo.ShapedParallel(env, api, task)
        venv = ss.pettingzoo_env_to_vec_env_v1(shaped)
        venv = ss.concat_vec_envs_v1(
            venv, copies, num_cpus=ns.num_cpus, base_class="stable_baselines3"
        )
        # SuperSuit's SB3 vector env has no seed(): seed the learner, not PPO(seed=...).
        set_random_seed(ns.seed)
        returns = EnvReturns()
        try:
            model = PPO(
                "MlpPolicy",
                venv,
                n_steps=n_steps,
                batch_size=n_steps * copies * N_AGENTS // 4,
                device="cpu",
                verbose=0,
            )
            model.learn(timesteps, callback=returns)
        finally:
            venv.close()  # SuperSuit's copies (and worker processes) close their sessions
            shaped.close()  # the original's sessions shaped nothing: SuperSuit used copies

        print(f"PPO, {N_AGENTS} agents sharing one policy, {copies} env copies, {ns.layout} pool")
        last = returns.returns[-60:]
        print(
            f"trained {model.num_timesteps} agent-steps, {len(returns.returns)} agent-episodes; "
            f"last-{len(last)} mean env return {np.mean(last):.2f}"
        )
        for task_id in task_ids:
            stats = api.get_task(task_id).stats
            print(
                f"task {task_id}: {stats.episodes_completed} episodes, "
                f"{stats.steps_shaped} steps shaped, pool {stats.pool_size} "
                f"(best score {stats.best_score:.2f})"
            )


if __name__ == "__main__":
    main()
