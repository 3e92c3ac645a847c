"""The regime study's environments, registered as gymnasium ids on import.

- ``TamrmRegimes/Maze-v0`` (E1): the reproduction's 8x8 maze with an 80-step cap, where a
  uniformly random walk reaches the goal in about 2.4 % of episodes. Reward on reaching
  the goal ``1 - 0.9 * steps / cap`` (MiniGrid's rule: shorter is better, and the
  episodic return ranks episodes), 0 otherwise. Observation: the cell, one-hot (64).
  Deterministic from a fixed start. ``sticky`` > 0 wraps it in gymnasium's
  ``StickyAction`` (the previous action is repeated with that probability): the mechanism
  control, where an action prefix no longer names a state.
- ``TamrmRegimes/DecoyMaze-v0`` (E3): the same maze with a decoy: a dead-end cell four
  moves from the start, off every shortest path, that ends the episode with a small reward
  (0.1). A random walk ends on the decoy before the goal in most of its successes.
- ``TamrmRegimes/DoorKey-v0`` (E2): MiniGrid's DoorKey of ``size``, observation the
  agent's 7x7 view flattened (147 values); ``layout_seed`` set: every episode is that one
  layout (reset always reseeds with it), else a new layout each episode (MiniGrid's own
  procedural generation) as the control. ``is_success`` on the last step: the goal reached.

Every env puts ``is_success`` in the info of an episode's last step.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np

from tamrm_experiments.envs import MAZE_GOAL, MAZE_MOVES, MAZE_SIZE, MAZE_START, MazeEnv

__all__ = [
    "DECOY_CELL",
    "DECOY_REWARD",
    "MAZE_CAP",
    "RegimeMaze",
    "goal_return",
    "make_doorkey",
    "make_maze",
    "random_walk_success",
    "shortest_paths",
]

#: E1's step cap: a random walk succeeds in about 2.4 % of episodes.
MAZE_CAP = 80
#: E3's decoy: a dead end four moves from the start, beside two cells of shortest paths
#: and on none.to the goal.
DECOY_CELL = (2, 5)
DECOY_REWARD = 0.1


def goal_return(steps: int, cap: int) -> float:
    """The return of reaching the goal in ``steps`` moves (MiniGrid's rule)."""
    return 1.0 - 0.9 * steps / cap


class RegimeMaze(MazeEnv):
    """The maze with a graded goal reward, a one-hot cell observation and an optional decoy."""

    def __init__(self, max_steps: int = MAZE_CAP, decoy: bool = False) -> None:
        super().__init__(max_steps=max_steps)
        self.decoy = decoy
        self.observation_space = gym.spaces.Box(0.0, 1.0, (MAZE_SIZE * MAZE_SIZE,), np.float32)

    def _obs(self) -> np.ndarray:
        out = np.zeros(MAZE_SIZE * MAZE_SIZE, dtype=np.float32)
        out[self.pos[1] * MAZE_SIZE + self.pos[0]] = 1.0
        return out

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move; the goal pays by speed, the decoy a little, and both end the episode."""
        obs, reward, terminated, truncated, info = super().step(action)
        info.pop("episode_score", None)
        if terminated:
            reward = goal_return(self.steps, self.max_steps)
        elif self.decoy and self.pos == DECOY_CELL:
            reward, terminated, truncated = DECOY_REWARD, True, False
            info["is_success"] = False
        return obs, reward, terminated, truncated, info


def make_maze(cap: int = MAZE_CAP, sticky: float = 0.0, decoy: bool = False) -> gym.Env[Any, Any]:
    """E1 (``decoy=False``) or E3, with sticky actions when ``sticky`` > 0."""
    env: gym.Env[Any, Any] = RegimeMaze(cap, decoy)
    if sticky > 0:
        env = gym.wrappers.StickyAction(env, repeat_action_probability=sticky)
    return env


class _FixedLayout(gym.Wrapper[Any, Any, Any, Any]):
    """Every reset reseeds the env with ``layout_seed``: one layout for every episode."""

    def __init__(self, env: gym.Env[Any, Any], layout_seed: int) -> None:
        super().__init__(env)
        self.layout_seed = layout_seed

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        return self.env.reset(seed=self.layout_seed, options=options)


class _Success(gym.Wrapper[Any, Any, Any, Any]):
    """``is_success`` on an episode's last step: a positive reward (MiniGrid's goal)."""

    def step(self, action: Any) -> Any:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info["is_success"] = bool(terminated and float(reward) > 0)
        return obs, reward, terminated, truncated, info


def make_doorkey(size: int = 5, layout_seed: int | None = None) -> gym.Env[Any, Any]:
    """E2: MiniGrid DoorKey, the 7x7 view flattened; one layout when ``layout_seed`` is set."""
    import minigrid  # noqa: F401  (registers the MiniGrid ids)
    from minigrid.wrappers import ImgObsWrapper

    env: gym.Env[Any, Any] = gym.make(f"MiniGrid-DoorKey-{size}x{size}-v0")
    env = gym.wrappers.FlattenObservation(ImgObsWrapper(env))
    if layout_seed is not None:
        env = _FixedLayout(env, layout_seed)
    return _Success(env)


def _open(cell: tuple[int, int]) -> bool:
    from tamrm_experiments.envs import MAZE_WALLS

    x, y = cell
    return 0 <= x < MAZE_SIZE and 0 <= y < MAZE_SIZE and cell not in MAZE_WALLS


def _distances(source: tuple[int, int]) -> dict[tuple[int, int], int]:
    dist = {source: 0}
    frontier = deque([source])
    while frontier:
        cell = frontier.popleft()
        for dx, dy in MAZE_MOVES:
            nxt = (cell[0] + dx, cell[1] + dy)
            if _open(nxt) and nxt not in dist:
                dist[nxt] = dist[cell] + 1
                frontier.append(nxt)
    return dist


def shortest_paths(
    start: tuple[int, int] = MAZE_START, goal: tuple[int, int] = MAZE_GOAL
) -> list[list[int]]:
    """Every shortest action sequence from ``start`` to ``goal``, in lexicographic order."""
    to_goal = _distances(goal)
    paths: list[list[int]] = []

    def walk(cell: tuple[int, int], prefix: list[int]) -> None:
        if cell == goal:
            paths.append(list(prefix))
            return
        for action, (dx, dy) in enumerate(MAZE_MOVES):
            nxt = (cell[0] + dx, cell[1] + dy)
            if _open(nxt) and to_goal.get(nxt) == to_goal[cell] - 1:
                prefix.append(action)
                walk(nxt, prefix)
                prefix.pop()

    walk(start, [])
    return paths


def random_walk_success(cap: int = MAZE_CAP, decoy: bool = False) -> float:
    """Probability that a uniformly random walk from the start reaches the goal within
    ``cap`` moves (exact, by dynamic programming over the cells; the decoy absorbs)."""
    cells = [(x, y) for y in range(MAZE_SIZE) for x in range(MAZE_SIZE) if _open((x, y))]
    index = {c: i for i, c in enumerate(cells)}
    p = np.zeros(len(cells))
    p[index[MAZE_START]] = 1.0
    reached = 0.0
    for _ in range(cap):
        nxt = np.zeros_like(p)
        for c, i in index.items():
            if p[i] == 0.0:
                continue
            for dx, dy in MAZE_MOVES:
                cell = (c[0] + dx, c[1] + dy)
                nxt[index[cell if _open(cell) else c]] += 0.25 * p[i]
        reached += nxt[index[MAZE_GOAL]]
        nxt[index[MAZE_GOAL]] = 0.0
        if decoy:
            nxt[index[DECOY_CELL]] = 0.0
        p = nxt
    return float(reached)


_MAKERS: dict[str, Any] = {"maze": make_maze, "doorkey": make_doorkey}
gym.register("TamrmRegimes/Maze-v0", entry_point=_MAKERS["maze"])
gym.register("TamrmRegimes/DecoyMaze-v0", entry_point=_MAKERS["maze"], kwargs={"decoy": True})
gym.register("TamrmRegimes/DoorKey-v0", entry_point=_MAKERS["doorkey"])
