"""gymnasium's own checker on the wrappers."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env

import tamrm
import tamrm.gym


class Corridor(gym.Env[np.ndarray, np.int64]):
    """A tiny deterministic env whose render needs no extra package (CartPole's needs pygame)."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, length: int = 6) -> None:
        self.render_mode = render_mode
        self.length = length
        self.observation_space = spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32)
        self.action_space = spaces.Discrete(2)
        self.pos = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.pos / self.length], dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.pos = int(self.np_random.integers(0, 2))
        return self._obs(), {}

    def step(self, action: np.int64) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.pos = max(0, self.pos + (1 if int(action) == 1 else -1))
        done = self.pos >= self.length
        return self._obs(), 1.0 if done else 0.0, done, False, {}

    def render(self) -> Any:
        if self.render_mode == "ansi":
            return "." * self.pos + "@" + "." * (self.length - self.pos)
        if self.render_mode == "rgb_array":
            return np.zeros((4, 4, 3), dtype=np.uint8)
        return None


gym.register("tamrm-test/Corridor-v0", entry_point=Corridor, max_episode_steps=20)


@pytest.mark.parametrize("value_fn", [None, lambda obs: np.asarray(obs)[:, 0] * 2.0])
def test_check_env_passes_with_default_arguments(
    client: tamrm.Client, task_id: str, value_fn: Any
) -> None:
    client.create_task(task_id, num_actions=2, min_pool_size=1, start_step=1)
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(gym.make("tamrm-test/Corridor-v0"), session, value_fn)
        check_env(env)
        # The wrapper still works after the checker (its recreated copies shared the session).
        assert not session.closed
        env.reset(seed=0)
        _, _, _, _, info = env.step(1)
        assert info["shaping_step"] == 0


def test_spec_make_recreates_the_wrapper(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    with client.session(task_id) as session:
        env = tamrm.gym.ShapedReward(
            gym.make("tamrm-test/Corridor-v0"), session, env_id=0, score_key="score"
        )
        assert env.spec is not None
        again = env.spec.make()
        assert isinstance(again, tamrm.gym.ShapedReward)
        assert again.session is session
        assert again.score_key == "score"
        again.reset(seed=1)
        again.close()
        assert not session.closed  # borrowed by the copy, not closed by it


def test_check_env_cartpole(client: tamrm.Client, task_id: str) -> None:
    # CartPole's render needs pygame (not a dependency); everything else is checked.
    client.create_task(task_id, num_actions=2)
    with client.session(task_id) as session:
        check_env(tamrm.gym.ShapedReward(gym.make("CartPole-v1"), session), skip_render_check=True)
