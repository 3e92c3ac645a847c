"""The ``authors`` fidelity: the authors' training loops, with the tamrm server shaping.

One episode loop per learner, as in the authors' scripts (``Carpole_test/carpole.py``,
``MountainCar_test/run_MountainCar.py``): act, step the environment, send the step to
the server (with the learner's own values for the potential term), override the reward
of a terminal step as they do, learn. The server computes ``R + alpha r(t) + beta F``
with ``gate_potential`` (their code adds both terms only inside the kNN window); the
loop recomputes the same sum from the returned parts and checks it against the server's
reward, so a run also tests the server's gating.

Differences to their code that remain (the server follows SPEC.md, see
``tests/test_authors_formula.py`` for r(t) itself): their window ends one step earlier
(``t < L_min - 1``; SPEC: ``t < L_min``); their pool replaces the worst trajectory on a
tie (``<=``; SPEC: strictly better); F of a terminal step uses V(s') = 0 (theirs: the
network's V(s')), which only matters on the terminal step, whose reward both override.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from tamrm_experiments.configs import EXPERIMENTS, RunSpec
from tamrm_experiments.learners import ActorCritic, TutorialDQN

__all__ = ["make_authors_env", "train_authors"]


def make_authors_env(spec: RunSpec) -> Any:
    """The authors' environment: unwrapped (no Gym time limit); the loop caps episodes."""
    import gymnasium as gym

    env_id = {"cartpole": "CartPole-v1", "mountaincar": "MountainCar-v0"}[
        EXPERIMENTS[spec.experiment].env
    ]
    return gym.make(env_id).unwrapped


class ShapingMismatch(AssertionError):
    """The server's reward differs from R + alpha r + beta F (gated) of its own parts."""


def train_authors(
    spec: RunSpec,
    session: Any,
    record: Callable[[dict[str, Any]], None],
    gate_on_server: bool,
) -> dict[str, Any]:
    """Train ``spec``'s learner for its budget, shaping every step through ``session``.

    ``record`` gets one dict per finished episode (the CSV row's fields that the loop
    knows). ``gate_on_server``: the task was created with ``gate_potential``; otherwise
    the loop applies the gate itself to the returned parts (a server without v1.1).
    Returns totals (episodes, total_steps, stopped_by_steps).
    """
    exp = EXPERIMENTS[spec.experiment]
    var = exp.variant(spec.variant)
    settings = var.settings
    cfg = spec.task_config()
    alpha, beta, gate = cfg["alpha"], cfg["beta"], cfg["gate_potential"]
    budget = spec.budget
    rng = np.random.default_rng(spec.seed)
    env = make_authors_env(spec)
    n_features = env.observation_space.shape[0]
    n_actions = int(env.action_space.n)
    learner: ActorCritic | TutorialDQN
    if settings["learner"] == "actor_critic":
        learner = ActorCritic(n_features, n_actions, rng, gamma=cfg["gamma"])
    else:
        learner = TutorialDQN(n_features, n_actions, rng, gamma=cfg["gamma"])
    terminal_reward = float(settings["terminal_reward"])
    fixed_start = bool(settings.get("fixed_start", False))
    freeze = bool(settings.get("freeze_when_solved", False))
    success_is_truncation = exp.env == "cartpole"
    total_steps = 0
    lengths: list[int] = []
    obs, _ = env.reset(seed=spec.seed)
    frozen = False
    for episode in range(1, budget.episodes + 1):
        if episode > 1:
            obs, _ = env.reset(seed=spec.seed if fixed_start else None)
        ep = {"steps": 0, "env_return": 0.0, "shaped": 0.0, "knn": 0.0, "pot": 0.0, "active": 0}
        terminated = truncated = False
        pool_version = 0
        while not (terminated or truncated):
            action = learner.act(obs)
            obs_next, r_env, terminated, _trunc, _info = env.step(action)
            ep["steps"] += 1
            total_steps += 1
            truncated = not terminated and (
                ep["steps"] >= budget.max_episode_steps or total_steps >= budget.max_total_steps
            )
            values = next_values = None
            if beta != 0.0:
                if isinstance(learner, ActorCritic):
                    v, v_next = learner.value(obs), learner.value(obs_next)
                else:  # theirs: max Q(s) of the online net, max Q(s') of the target net
                    v = float(learner.q_values(obs).max())
                    v_next = float(learner.target_q_values(obs_next).max())
                values, next_values = [v], [v_next]
            res = session.step(
                [action],
                [float(r_env)],
                [terminated],
                [truncated],
                values=values,
                next_values=next_values,
            )
            knn, pot, active = (
                float(res.knn_rewards[0]),
                float(res.potentials[0]),
                bool(res.knn_active[0]),
            )
            mine = float(r_env) + alpha * knn + beta * pot * (active if gate else 1.0)
            shaped = float(res.rewards[0]) if gate_on_server else mine
            if abs(shaped - mine) > 1e-6 * max(1.0, abs(mine)):
                raise ShapingMismatch(
                    f"{spec.key} step {total_steps}: server {shaped} != R + a r + b F = {mine}"
                )
            pool_version = res.pool_version
            reward = terminal_reward if terminated else shaped  # their override, after shaping
            if isinstance(learner, ActorCritic):
                learner.learn(obs, action, reward, obs_next)
            else:
                learner.observe(obs, action, reward, obs_next)
            ep["env_return"] += float(r_env)
            ep["shaped"] += reward
            ep["knn"] += knn
            ep["pot"] += pot
            ep["active"] += int(active)
            obs = obs_next
        lengths.append(ep["steps"])
        record(
            {
                "episode": episode,
                "steps": ep["steps"],
                "env_return": ep["env_return"],
                "shaped_return": round(ep["shaped"], 6),
                "knn_sum": round(ep["knn"], 6),
                "potential_sum": round(ep["pot"], 6),
                "knn_active_steps": ep["active"],
                "terminated": int(terminated),
                "truncated": int(truncated),
                "success": int(truncated if success_is_truncation else terminated),
                "score": ep["env_return"],
                "task_phase": 0,
                "pool_version": pool_version,
                "total_steps": total_steps,
            }
        )
        # Their "solved" rule (cart pole): mean of the last 100 episodes >= 195.
        if freeze and not frozen and len(lengths) >= 100 and np.mean(lengths[-100:]) >= 195:
            learner.freeze()  # type: ignore[union-attr]
            frozen = True
        if total_steps >= budget.max_total_steps:
            return {"episodes": episode, "total_steps": total_steps, "stopped_by_steps": True}
    env.close()
    return {"episodes": budget.episodes, "total_steps": total_steps, "stopped_by_steps": False}
