"""Environments registered for the trial's tests (``--env-module trial_envs``)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class Corridor(gym.Env[np.ndarray, int]):
    """A corridor of ``length`` cells: action 1 moves right, 0 left; +1 at the end.

    Episodes are cut at ``4 * length`` steps. Deterministic, and fast enough for tests.
    """

    def __init__(self, length: int = 6) -> None:
        self.length = length
        self.observation_space = gym.spaces.Box(0.0, 1.0, (1,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.pos = 0
        self.steps = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.pos / self.length], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        super().reset(seed=seed)
        self.pos = self.steps = 0
        return self._obs(), {}

    def step(self, action: int) -> Any:
        self.pos = max(0, self.pos + (1 if int(action) == 1 else -1))
        self.steps += 1
        done = self.pos >= self.length
        return self._obs(), float(done), done, self.steps >= 4 * self.length, {}


class Crashing(Corridor):
    """A corridor that raises on its 50th step when it was first seeded with 1."""

    def __init__(self) -> None:
        super().__init__()
        self.first_seed: int | None = None
        self.total = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        if self.first_seed is None and seed is not None:
            self.first_seed = seed
        return super().reset(seed=seed, options=options)

    def step(self, action: int) -> Any:
        self.total += 1
        if self.first_seed == 1 and self.total == 50:
            raise RuntimeError("the test env broke on purpose")
        return super().step(action)


class Grid(Corridor):
    """A corridor whose actions are a MultiDiscrete pair: a task cannot take them."""

    def __init__(self) -> None:
        super().__init__()
        self.action_space = gym.spaces.MultiDiscrete([2, 2])  # type: ignore[assignment]


gym.register("TamrmTest/Corridor-v0", entry_point=Corridor)
gym.register("TamrmTest/Crashing-v0", entry_point=Crashing)
gym.register("TamrmTest/Grid-v0", entry_point=Grid)
