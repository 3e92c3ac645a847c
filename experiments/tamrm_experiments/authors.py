"""The ``authors`` fidelity: the authors' training loops, with tamrm shaping.

One episode loop per learner, as in the authors' scripts (``Carpole_test/carpole.py``,
``MountainCar_test/run_MountainCar.py``): act, step the environment, send the step to
tamrm (its embedded engine or a server; with the learner's own values for the potential
term), override the reward of a terminal step as they do, learn. tamrm computes
``R + alpha r(t) + beta F`` with ``gate_potential`` (their code adds both terms only
inside the kNN window); the loop recomputes the same sum from the returned parts and
checks it against tamrm's reward, so a run also tests tamrm's gating.

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


def make_authors_env(spec: RunSpec, settings: dict[str, Any] | None = None) -> Any:
    """The authors' environment: unwrapped (no Gym time limit; the loop caps episodes),
    and for the maze their observation, the agent's 4 canvas coordinates in pixels, or
    with ``settings["observation"] == "onehot"`` the cell one-hot (64 inputs)."""
    import gymnasium as gym

    env = EXPERIMENTS[spec.experiment].env
    if env.startswith("maze"):
        from tamrm_experiments.envs import MazeEnv, OneHotCell

        maze = MazeEnv(
            max_steps=spec.budget.max_episode_steps,
            switch_start_after=spec.budget.switch_after,
        )
        if (settings or {}).get("observation") == "onehot":
            return OneHotCell(maze)
        return CanvasCoords(maze)
    return gym.make({"cartpole": "CartPole-v1", "mountaincar": "MountainCar-v0"}[env]).unwrapped


class CanvasCoords:
    """Their maze's observation (``maze_env.py``): the agent's rectangle on a 40-pixel grid,
    ``[40x + 2, 40y + 2, 40x + 38, 40y + 38]``. Same layout, start and goal as ours."""

    def __init__(self, env: Any) -> None:
        import gymnasium as gym

        self.env = env
        self.action_space = env.action_space
        self.observation_space = gym.spaces.Box(0.0, 320.0, (4,), np.float32)

    @staticmethod
    def coords(obs: np.ndarray) -> np.ndarray:
        """(x, y) -> the 4 canvas coordinates."""
        x, y = float(obs[0]), float(obs[1])
        return np.array([40 * x + 2, 40 * y + 2, 40 * x + 38, 40 * y + 38])

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return self.coords(obs), info

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, r, term, trunc, info = self.env.step(action)
        return self.coords(obs), r, term, trunc, info

    def close(self) -> None:
        self.env.close()


class ScaledObservation:
    """``env`` with its observations divided by ``scale``."""

    def __init__(self, env: Any, scale: float) -> None:
        self.env, self.scale = env, scale
        self.action_space = env.action_space
        self.observation_space = env.observation_space

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return np.asarray(obs, np.float64) / self.scale, info

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, r, term, trunc, info = self.env.step(action)
        return np.asarray(obs, np.float64) / self.scale, r, term, trunc, info

    def close(self) -> None:
        self.env.close()


def _make_learner(
    settings: dict[str, Any], n_features: int, n_actions: int, rng: Any, gamma: float
):
    kind = settings["learner"]
    # A variant may change the learner's settings (``learner_kwargs``: a tuned variant).
    extra = dict(settings.get("learner_kwargs", {}))
    if kind == "actor_critic":
        return ActorCritic(n_features, n_actions, rng, gamma=gamma, **extra)
    if kind == "maze_dqn":  # Maze_grid/RL_brain.py and run_maze.py
        kwargs = {
            "lr": 0.01,
            "greedy_increment": None,
            "replace_target_iter": 200,
            "memory_size": 20_000,
            "hidden": 10,
            "optimizer": "adam",
        }
        return TutorialDQN(n_features, n_actions, rng, gamma=gamma, **{**kwargs, **extra})
    return TutorialDQN(n_features, n_actions, rng, gamma=gamma, **extra)


class ShapingMismatch(AssertionError):
    """The server's reward differs from R + alpha r + beta F (gated) of its own parts."""


def train_authors(
    spec: RunSpec,
    session: Any,
    record: Callable[[dict[str, Any]], None],
    gate_on_server: bool,
    settings: dict[str, Any] | None = None,
    switch_task: Callable[[], Any] | None = None,
) -> dict[str, Any]:
    """Train ``spec``'s learner for its budget, shaping every step through ``session``.

    ``record`` gets one dict per finished episode (the CSV row's fields that the loop
    knows). ``gate_on_server``: the task was created with ``gate_potential``; otherwise
    the loop applies the gate itself to the returned parts (a server without v1.1).
    ``settings``: the variant's settings to use instead of ``spec``'s (the pilots try
    changes to a learner this way, ``tamrm_experiments.pilot``). ``switch_task``: called
    after episode ``budget.switch_after`` (the modified maze, whose start then moves), it
    returns the session of a new task with a fresh pool, used from then on.
    Returns totals (episodes, total_steps, stopped_by_steps).
    """
    exp = EXPERIMENTS[spec.experiment]
    if settings is None:
        settings = exp.variant(spec.variant).settings
    cfg = spec.task_config()
    alpha, beta, gate = cfg["alpha"], cfg["beta"], cfg["gate_potential"]
    budget = spec.budget
    rng = np.random.default_rng(spec.seed)
    env = make_authors_env(spec, settings)
    # A tuned variant may scale the observation (e.g. the maze's pixel coordinates).
    obs_scale = settings.get("obs_scale")
    if obs_scale is not None:
        env = ScaledObservation(env, float(obs_scale))
    n_features = env.observation_space.shape[0]
    n_actions = int(env.action_space.n)
    learner = _make_learner(settings, n_features, n_actions, rng, cfg["gamma"])
    terminal_reward = settings.get("terminal_reward")
    timeout_reward = settings.get("timeout_reward")
    # Their maze's run_maze.py never updates its observation (``ob_ = ob``): the agent
    # acts on, stores and evaluates the start cell's observation at every step.
    observation_bug = bool(settings.get("observation_bug", False))
    maze_score = exp.env.startswith("maze")
    fixed_start = bool(settings.get("fixed_start", False))
    freeze = bool(settings.get("freeze_when_solved", False))
    success_is_truncation = exp.env == "cartpole"
    total_steps = 0
    lengths: list[int] = []
    obs, _ = env.reset(seed=spec.seed)
    frozen = False
    phase = 0
    for episode in range(1, budget.episodes + 1):
        if episode > 1:
            obs, _ = env.reset(seed=spec.seed if fixed_start else None)
        ep = {"steps": 0, "env_return": 0.0, "shaped": 0.0, "knn": 0.0, "pot": 0.0, "active": 0}
        terminated = truncated = False
        pool_version = 0
        start_obs = obs
        while not (terminated or truncated):
            if observation_bug:
                obs = start_obs
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
            scores = None
            if maze_score and (terminated or truncated):
                # Theirs: state_record.append(r * 100 / t), r = +1 at the goal, -1 on the
                # time-out; t counts the steps before the last one.
                last = 1.0 if terminated else -1.0
                scores = [last * 100.0 / max(1, ep["steps"] - 1)]
            res = session.step(
                [action],
                [float(r_env)],
                [terminated],
                [truncated],
                values=values,
                next_values=next_values,
                episode_scores=scores,
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
            reward = shaped
            if terminated and terminal_reward is not None:
                reward = float(terminal_reward)  # their override, after the shaping
            elif truncated and timeout_reward is not None:
                reward = float(timeout_reward)
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
        lengths.append(int(ep["steps"]))
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
                "score": scores[0] if scores else ep["env_return"],
                "task_phase": phase,
                "pool_version": pool_version,
                "total_steps": total_steps,
            }
        )
        # Their "solved" rule (cart pole): mean of the last 100 episodes >= 195.
        if freeze and not frozen and len(lengths) >= 100 and np.mean(lengths[-100:]) >= 195:
            learner.freeze()
            frozen = True
        if budget.switch_after is not None and episode == budget.switch_after:
            if switch_task is None:
                raise ValueError(
                    f"{spec.key}: the start moves after episode "
                    f"{budget.switch_after}: give switch_task"
                )
            session = switch_task()
            phase += 1
        if total_steps >= budget.max_total_steps:
            return {"episodes": episode, "total_steps": total_steps, "stopped_by_steps": True}
    env.close()
    return {"episodes": budget.episodes, "total_steps": total_steps, "stopped_by_steps": False}
