#!/usr/bin/env python3
"""RLlib PPO (new API stack) on a two-agent CartPole, shaped by one tamrm server.

Two EnvRunner actors sample the multi-agent env; each has one tamrm client and local
sessions (SPEC §13): the kNN term alpha * r(t) is computed on the EnvRunner
(``tamrm.rllib.knn_connector``) and only episode ends travel to the server, which every
EnvRunner shares. The learner adds beta * F from PPO's own critic
(``tamrm.rllib.potential_connector``). Each agent trains its own policy; ``--tasks
shared`` gives both agents one pool, ``--tasks per-agent`` (default) one each.

    python clients/python/examples/rllib_ppo.py              # a local server, 20 iterations
    python clients/python/examples/rllib_ppo.py --quick      # smoke test: 2 tiny iterations
    python clients/python/examples/rllib_ppo.py --server 127.0.0.1:50051 --remote

At the end the EnvRunners' sessions are closed (a local session reports its last steps
when it closes) and the server's counters are checked against what RLlib sampled: every
agent step RLlib recorded was shaped once, and every agent episode that ended reached
the pool update (the episodes still running when sampling stopped may have ended some of
their agents already).
"""

from __future__ import annotations

import argparse
import contextlib
import uuid
from collections.abc import Iterator
from typing import Any

import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.examples.envs.classes.multi_agent import MultiAgentCartPole

import tamrm
import tamrm.rllib

NUM_AGENTS = 2


@contextlib.contextmanager
def server_address(address: str | None) -> Iterator[str]:
    """``address``, or a local in-memory server's for the run."""
    if address is not None:
        yield address
        return
    with tamrm.local_server(in_memory=True) as local:
        yield local.address


def build(ns: argparse.Namespace, address: str, tasks: dict[int, str]) -> Any:
    """The PPO config: two EnvRunners, one policy per agent, tamrm on both sides."""
    with tamrm.Client(address) as client:
        task = client.get_task(tasks[0])
    quick = ns.quick
    return (
        PPOConfig()
        .api_stack(enable_rl_module_and_learner=True, enable_env_runner_and_connector_v2=True)
        .environment(MultiAgentCartPole, env_config={"num_agents": NUM_AGENTS})
        .multi_agent(
            policies={f"p{i}" for i in range(NUM_AGENTS)},
            policy_mapping_fn=lambda agent_id, episode, **kwargs: f"p{agent_id}",
        )
        .env_runners(
            num_env_runners=2,
            num_envs_per_env_runner=1,
            num_cpus_per_env_runner=0,
            rollout_fragment_length=64 if quick else 200,
            # The kNN term on each EnvRunner: agent i's steps go to tasks[i].
            env_to_module_connector=tamrm.rllib.knn_connector(
                tasks.__getitem__, address=address, local=not ns.remote
            ),
        )
        .learners(
            num_learners=0,
            # beta * F with the learner's critic; beta and gamma are the task's.
            learner_connector=tamrm.rllib.potential_connector(task),
        )
        .training(
            train_batch_size_per_learner=128 if quick else 2000,
            minibatch_size=64 if quick else 250,
            num_epochs=2 if quick else 6,
            lr=3e-4,
        )
        .debugging(seed=ns.seed)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--tasks", choices=["per-agent", "shared"], default="per-agent")
    parser.add_argument("--remote", action="store_true", help="remote sessions, not local")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="smoke test: 2 tiny iterations")
    ns = parser.parse_args()
    iterations = 2 if ns.quick else ns.iterations

    with server_address(ns.server) as address, tamrm.Client(address) as client:
        run = uuid.uuid4().hex[:8]
        if ns.tasks == "shared":
            tasks = dict.fromkeys(range(NUM_AGENTS), f"rllib-cartpole/{run}")
        else:
            tasks = {i: f"rllib-cartpole/{run}/agent-{i}" for i in range(NUM_AGENTS)}
        for task_id in set(tasks.values()):
            client.create_task(task_id, num_actions=2, pool_capacity=20, min_pool_size=5)

        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            algo = build(ns, address, tasks).build_algo()
            try:
                for i in range(iterations):
                    result = algo.train()
                    runners = result["env_runners"]
                    shaped = runners.get("episode_return_mean", float("nan"))
                    env_return = runners.get("tamrm", {}).get(
                        "env_episode_return_mean", float("nan")
                    )
                    print(
                        f"iteration {i + 1}: episodes {int(runners['num_episodes_lifetime'])}, "
                        f"return (env) {env_return:.1f}, return (shaped) {shaped:.1f}"
                    )
                per_runner = algo.env_runner_group.foreach_env_runner(
                    tamrm.rllib.close_sessions, local_env_runner=False
                )
                sampled = int(sum(runners["num_agent_steps_sampled_lifetime"].values()))
                episodes = int(runners["num_episodes_lifetime"])
            finally:
                algo.stop()
        finally:
            ray.shutdown()

        stats = [client.get_task(t).stats for t in set(tasks.values())]
        steps = sum(s.steps_shaped for s in stats)
        ends = sum(s.episodes_completed for s in stats)
        for index, counts in enumerate(per_runner, start=1):
            print(
                f"EnvRunner {index}: {counts.agent_steps} agent steps, "
                f"{counts.episodes} agent episodes ended"
            )
        print(
            f"server: steps_shaped {steps}, episodes_completed {ends}; RLlib sampled "
            f"{sampled} agent steps, {episodes} episodes of {NUM_AGENTS} agents"
        )
        assert len(per_runner) == 2 and all(c.agent_steps > 0 for c in per_runner), per_runner
        assert steps == sampled == sum(c.agent_steps for c in per_runner)
        assert ends == sum(c.episodes for c in per_runner)
        # Every agent of an ended episode ended its own; an episode still running when
        # sampling stopped may have ended some agents (one episode per EnvRunner here).
        assert NUM_AGENTS * episodes <= ends <= NUM_AGENTS * episodes + 2 * (NUM_AGENTS - 1)
        print("every agent step and agent episode reached the server once")


if __name__ == "__main__":
    main()
