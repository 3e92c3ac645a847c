"""The environments of the paper's three experiments (paper §V), as gymnasium envs.

- :class:`MazeEnv`: the 8x8 maze of Fig. 7 (and the modified maze of Fig. 9 through
  ``switch_start_after``).
- :class:`PaperCartPoleReward`: ``CartPole-v0`` (200-step episodes) with the paper's
  training reward: +1 per step, -1 on the step where the pole falls / the cart leaves.
- :func:`make_mountain_car`: ``MountainCar-v0`` dynamics without Gym's 200-step limit,
  capped at ``max_steps`` steps per episode (a truncation, not a termination).
"""

from __future__ import annotations

from collections import deque
from typing import Any, cast

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import TimeLimit

__all__ = [
    "MAZE_GOAL",
    "MAZE_NEW_START",
    "MAZE_SIZE",
    "MAZE_START",
    "MAZE_WALLS",
    "MazeEnv",
    "OneHotCell",
    "PaperCartPoleReward",
    "make_cartpole",
    "make_maze",
    "make_maze_onehot",
    "make_mountain_car",
    "maze_random_walk_steps",
    "maze_shortest_path",
    "mountain_car_random_steps",
    "random_policy_steps",
]

MAZE_SIZE = 8
#: Wall cells as (x, y): x is the column, y the row counted from the top.
MAZE_WALLS: frozenset[tuple[int, int]] = frozenset(
    {
        (5, 0),
        (1, 1),
        (7, 1),
        (0, 2),
        (1, 2),
        (4, 2),
        (6, 2),
        (7, 2),
        (0, 4),
        (2, 4),
        (6, 4),
        (0, 5),
        (3, 5),
        (6, 5),
        (7, 5),
        (6, 6),
        (3, 7),
        (4, 7),
    }
)
MAZE_START = (0, 7)
MAZE_GOAL = (7, 0)
#: Start of the modified maze from episode ``switch_start_after + 1`` on (our choice: the
#: paper's Fig. 9 is not legible in the text we have). The bottom-right corner: on the
#: other side of the wall (3,7)-(4,7), reached by a different route.
MAZE_NEW_START = (7, 7)
#: Actions: 0 up (y - 1), 1 down (y + 1), 2 left (x - 1), 3 right (x + 1).
MAZE_MOVES: tuple[tuple[int, int], ...] = ((0, -1), (0, 1), (-1, 0), (1, 0))


def _open(cell: tuple[int, int]) -> bool:
    x, y = cell
    return 0 <= x < MAZE_SIZE and 0 <= y < MAZE_SIZE and cell not in MAZE_WALLS


def maze_shortest_path(start: tuple[int, int], goal: tuple[int, int] = MAZE_GOAL) -> int:
    """Return the number of moves of a shortest path from ``start`` to ``goal`` (BFS)."""
    seen = {start}
    frontier: deque[tuple[tuple[int, int], int]] = deque([(start, 0)])
    while frontier:
        cell, dist = frontier.popleft()
        if cell == goal:
            return dist
        for dx, dy in MAZE_MOVES:
            nxt = (cell[0] + dx, cell[1] + dy)
            if _open(nxt) and nxt not in seen:
                seen.add(nxt)
                frontier.append((nxt, dist + 1))
    raise ValueError(f"{goal} is not reachable from {start}")


class MazeEnv(gym.Env[np.ndarray, int]):
    """The paper's 8x8 maze: sparse reward +1 at the goal, 0 otherwise.

    A move into a wall or off the grid leaves the agent in place. An episode terminates
    at the goal and is truncated after ``max_steps`` steps. The observation is the
    agent's ``(x, y)`` as float32. The final step's ``info`` carries ``episode_score``:
    ``100 / steps`` on success (shorter paths rank higher in the memory pool), ``0.0``
    on a truncated failure, and ``is_success``.

    Args:
        max_steps: Steps after which an unfinished episode is truncated (paper: 10 000).
        start: The start cell.
        switch_start_after: If set, episodes after this many (counted by this env's
            resets) start at ``new_start`` instead: the paper's modified maze.
        new_start: The start cell after the switch.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        max_steps: int = 10_000,
        start: tuple[int, int] = MAZE_START,
        switch_start_after: int | None = None,
        new_start: tuple[int, int] = MAZE_NEW_START,
    ) -> None:
        super().__init__()
        for cell in (start, new_start):
            if not _open(cell):
                raise ValueError(f"start cell {cell} is a wall or off the grid")
        self.observation_space = gym.spaces.Box(0.0, MAZE_SIZE - 1.0, (2,), np.float32)
        self.action_space = cast("gym.spaces.Space[int]", gym.spaces.Discrete(4))
        self.max_steps = max_steps
        self.start = start
        self.switch_start_after = switch_start_after
        self.new_start = new_start
        self.episodes_started = 0
        self.pos = start
        self.steps = 0

    @property
    def current_start(self) -> tuple[int, int]:
        """The start cell of the current episode."""
        if self.switch_start_after is not None and self.episodes_started > self.switch_start_after:
            return self.new_start
        return self.start

    def _obs(self) -> np.ndarray:
        return np.array(self.pos, dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode at the (current) start cell."""
        super().reset(seed=seed)
        self.episodes_started += 1
        self.pos = self.current_start
        self.steps = 0
        return self._obs(), {"start": self.pos}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move one cell (or stay, blocked by a wall or the edge)."""
        dx, dy = MAZE_MOVES[int(action)]
        nxt = (self.pos[0] + dx, self.pos[1] + dy)
        if _open(nxt):
            self.pos = nxt
        self.steps += 1
        terminated = self.pos == MAZE_GOAL
        truncated = not terminated and self.steps >= self.max_steps
        info: dict[str, Any] = {}
        if terminated:
            info["episode_score"] = 100.0 / self.steps
            info["is_success"] = True
        elif truncated:
            info["episode_score"] = 0.0
            info["is_success"] = False
        return self._obs(), 1.0 if terminated else 0.0, terminated, truncated, info


class PaperCartPoleReward(gym.Wrapper[Any, Any, Any, Any]):
    """The paper's CartPole training reward: +1 per step, -1 on the failing step.

    A step that *terminates* the episode (pole past 12 degrees or cart off the track)
    gets -1; every other step, including the one truncated at the 200-step limit, +1.
    The metric (steps kept up) is the episode length, which is unchanged.
    """

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the env and replace its reward."""
        obs, _reward, terminated, truncated, info = self.env.step(action)
        return obs, (-1.0 if terminated else 1.0), terminated, truncated, info


def make_cartpole() -> gym.Env[Any, Any]:
    """``CartPole-v0`` (200-step limit) with the paper's training reward."""
    return PaperCartPoleReward(gym.make("CartPole-v0"))


def make_mountain_car(max_steps: int = 10_000) -> gym.Env[Any, Any]:
    """``MountainCar-v0`` dynamics without the 200-step limit, capped at ``max_steps``."""
    from gymnasium.envs.classic_control.mountain_car import MountainCarEnv

    return TimeLimit(MountainCarEnv(), max_episode_steps=max_steps)


def make_maze(max_steps: int = 10_000, switch_start_after: int | None = None) -> MazeEnv:
    """The maze (modified maze when ``switch_start_after`` is set)."""
    return MazeEnv(max_steps=max_steps, switch_start_after=switch_start_after)


class OneHotCell(gym.ObservationWrapper[np.ndarray, int, np.ndarray]):
    """The maze's observation as a one-hot vector of its 64 cells (index ``y * 8 + x``)."""

    def __init__(self, env: gym.Env[np.ndarray, int]) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Box(0.0, 1.0, (MAZE_SIZE * MAZE_SIZE,), np.float32)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        """(x, y) -> one-hot."""
        out = np.zeros(MAZE_SIZE * MAZE_SIZE, dtype=np.float32)
        out[int(observation[1]) * MAZE_SIZE + int(observation[0])] = 1.0
        return out


def make_maze_onehot(max_steps: int = 10_000, switch_start_after: int | None = None) -> OneHotCell:
    """The maze with a one-hot cell observation (the clean variant's learner input)."""
    return OneHotCell(make_maze(max_steps, switch_start_after))


def maze_random_walk_steps(start: tuple[int, int] = MAZE_START) -> float:
    """Expected steps of a uniformly random walk from ``start`` to the goal (exact: the
    hitting times solve ``E[c] = 1 + mean over the 4 moves of E[next cell]``)."""
    cells = [(x, y) for y in range(MAZE_SIZE) for x in range(MAZE_SIZE) if _open((x, y))]
    index = {c: i for i, c in enumerate(cells)}
    n = len(cells)
    a = np.eye(n)
    b = np.ones(n)
    for c, i in index.items():
        if c == MAZE_GOAL:
            b[i] = 0.0
            continue
        for dx, dy in MAZE_MOVES:
            nxt = (c[0] + dx, c[1] + dy)
            a[i, index[nxt if _open(nxt) else c]] -= 0.25
    return float(np.linalg.solve(a, b)[index[start]])


def mountain_car_random_steps(max_steps: int, episodes: int = 2000, seed: int = 0) -> np.ndarray:
    """Episode lengths of a uniformly random policy in ``MountainCar-v0``'s dynamics, capped
    at ``max_steps`` (a capped episode counts ``max_steps``).

    ``episodes`` episodes run side by side in numpy: the same update as gymnasium's
    ``MountainCarEnv.step`` (checked step by step in ``tests/test_envs.py``), fast enough
    for caps of 100 000 steps, where stepping the gymnasium env would take minutes."""
    rng = np.random.default_rng(seed)
    position = rng.uniform(-0.6, -0.4, episodes)
    velocity = np.zeros(episodes)
    steps = np.zeros(episodes, dtype=np.int64)
    running = np.ones(episodes, dtype=bool)
    for _ in range(max_steps):
        velocity, position = _mountain_car_step(position, velocity, rng.integers(0, 3, episodes))
        steps += running
        running &= ~((position >= 0.5) & (velocity >= 0.0))
        if not running.any():
            break
    return steps


def _mountain_car_step(
    position: np.ndarray, velocity: np.ndarray, action: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``MountainCarEnv.step``'s update, vectorised: (velocity, position) after ``action``."""
    velocity = np.clip(
        velocity + (action - 1) * 0.001 + np.cos(3 * position) * -0.0025, -0.07, 0.07
    )
    position = np.clip(position + velocity, -1.2, 0.6)
    velocity = np.where((position == -1.2) & (velocity < 0), 0.0, velocity)
    return velocity, position


def random_policy_steps(experiment: str, max_steps: int, after_switch: bool = False) -> float:
    """Mean steps per episode of a uniformly random policy: the floor a learner must beat.

    Maze: the exact random walk from the start (``after_switch``: the modified maze's new
    start). Mountain car: 2000 simulated episodes under the per-episode cap ``max_steps``.
    Cart pole: 2000 episodes of the gymnasium env, cut at ``max_steps``."""
    if experiment in ("maze", "maze_modified"):
        return maze_random_walk_steps(MAZE_NEW_START if after_switch else MAZE_START)
    if experiment == "mountaincar":
        return float(mountain_car_random_steps(max_steps).mean())
    if experiment == "cartpole":
        env: TimeLimit[Any, Any] = TimeLimit(
            gym.make("CartPole-v1").unwrapped, max_episode_steps=max_steps
        )
        env.action_space.seed(0)
        lengths = []
        for episode in range(2000):
            env.reset(seed=episode)
            n, done = 0, False
            while not done:
                _, _, terminated, truncated, _ = env.step(env.action_space.sample())
                n, done = n + 1, terminated or truncated
            lengths.append(n)
        return float(np.mean(lengths))
    raise ValueError(f"no random-policy reference for experiment {experiment!r}")
