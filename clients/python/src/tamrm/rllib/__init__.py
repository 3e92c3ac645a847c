"""Ray RLlib (new API stack): the kNN term on the EnvRunners, the potential term on the learners.

Two ConnectorV2 pieces split ``R_meta = R + alpha * r(t) + beta * F`` where the data is:

- :class:`KnnShaping`, an env-to-module piece, runs on every EnvRunner (single- or
  multi-agent). After each vector step it sends every agent step the EnvRunner just
  recorded (action, reward, terminated, truncated) to tamrm, one ``Session.step`` per task,
  and writes ``R + alpha * r(t)`` back into the episode, in place of the reward RLlib
  recorded. Each EnvRunner process has one :class:`tamrm.Client` and, per task, one session
  with a slot per (sub-environment, agent); by default a local session (SPEC §13), so a
  step never waits on the network and only episode ends reach the server.
- :class:`PotentialShaping`, a learner piece, adds ``beta * (gamma * V(s') - V(s))`` with
  the learner's own value function (``V(s') = 0`` after a terminated step, V of the real
  last observation after a truncated one), once per episode chunk: a chunk it has shaped
  is marked and never shaped again, and it writes to a copy of the rewards, never into
  arrays a replay buffer may share.

Wiring both::

    import tamrm, tamrm.rllib
    from ray.rllib.algorithms.ppo import PPOConfig

    task = tamrm.Client("shaping:50051").create_task("cartpole", num_actions=2)
    config = (
        PPOConfig()
        .environment("CartPole-v1")
        .env_runners(env_to_module_connector=tamrm.rllib.knn_connector("cartpole",
                                                                       address="shaping:50051"))
        .learners(learner_connector=tamrm.rllib.potential_connector(task))
    )

Multi-agent: ``task`` is a task id shared by every agent, or a function ``agent_id -> task
id`` (like ``policy_mapping_fn``: a pool per agent, role or team). Each agent's own
SingleAgentEpisode inside the MultiAgentEpisode is one tamrm episode: an agent that dies
ends its episode then (the pool update of SPEC §6), one that appears later starts its
episode at its first step, and the reward shaped is exactly the agent step's reward RLlib
trains on (rewards an agent receives between two of its observations included).
"""

from __future__ import annotations

# _pieces, POTENTIAL_MARK and _task_of are not in __all__; the tests reach them here.
from tamrm.gym import INFO_KEYS
from tamrm.rllib._clients import process_client
from tamrm.rllib._knn import (
    KnnShaping,
    _pieces,  # noqa: F401
    close_sessions,
    knn_connector,
)
from tamrm.rllib._potential import (
    POTENTIAL_MARK,  # noqa: F401
    PotentialShaping,
    potential_connector,
)
from tamrm.rllib._send import ShapingCounts
from tamrm.rllib._tasks import TaskMap
from tamrm.rllib._tasks import task_of as _task_of  # noqa: F401

__all__ = [
    "INFO_KEYS",
    "KnnShaping",
    "PotentialShaping",
    "ShapingCounts",
    "TaskMap",
    "close_sessions",
    "knn_connector",
    "potential_connector",
    "process_client",
]
