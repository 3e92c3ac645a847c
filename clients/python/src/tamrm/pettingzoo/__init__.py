"""PettingZoo wrappers: shape every agent's reward through tamrm (extra ``tamrm[pettingzoo]``).

One pool for every agent, or one per agent, role or team::

    engine = tamrm.Engine()
    engine.create_task("spread", num_actions=5)
    env = tamrm.pettingzoo.ShapedParallel(simple_spread_v3.parallel_env(), engine, "spread")

    # one task per role: ``task`` maps an agent to its task id
    env = tamrm.pettingzoo.ShapedParallel(env, engine, lambda agent: agent.split("_")[0])

The wrappers open one session per task, with one environment slot per agent of
``possible_agents`` mapped to it, and send each task's agents of a step in one batch.
An agent's episode starts at its first action and ends on its terminated or truncated
step (the pool update of SPEC §6); after that the agent is not shaped again until
``reset``, which abandons the episodes still unfinished (SPEC §12).

``ShapedParallel`` shapes the rewards ``step`` returns. ``ShapedAEC`` shapes what
``last()`` reports at an agent's turn: the reward accumulated since its previous turn,
as the outcome of the action it took then; an agent that terminated or truncated is
shaped at the turn on which it is removed (``step(None)``). Each shaped agent's
``infos[agent]`` gets the keys of :data:`tamrm.gym.INFO_KEYS`. docs/multi-agent.md tells
which pool layout to choose and how to train with SuperSuit and Stable-Baselines3.
"""

from __future__ import annotations

from tamrm.gym import INFO_KEYS
from tamrm.pettingzoo._pools import AgentValueFn, TaskMap
from tamrm.pettingzoo._wrappers import ShapedAEC, ShapedParallel

__all__ = ["INFO_KEYS", "AgentValueFn", "ShapedAEC", "ShapedParallel", "TaskMap"]
