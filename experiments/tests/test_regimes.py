"""The regime study's environments, baselines, grid and selection rule."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import tamrm_regimes.envs as envs
from tamrm_experiments.envs import MAZE_MOVES, MAZE_START
from tamrm_regimes.study import (
    VARIANTS,
    config_id,
    select,
    sil_grid,
    stage_a_grid,
    stage_b_grid,
)


def _walk(actions: list[int]) -> tuple[int, int]:
    cell = MAZE_START
    for a in actions:
        dx, dy = MAZE_MOVES[a]
        cell = (cell[0] + dx, cell[1] + dy)
    return cell


def test_random_walk_success_matches_simulation() -> None:
    """The exact random-walk success within 80 steps (~2.4 %) against simulated walks."""
    exact = envs.random_walk_success()
    assert 0.02 < exact < 0.03
    env = envs.make_maze()
    rng = np.random.default_rng(0)
    wins = 0
    n = 4000
    for _ in range(n):
        env.reset()
        done, reward = False, 0.0
        while not done:
            _, reward, terminated, truncated, _ = env.step(int(rng.integers(4)))
            done = terminated or truncated
        wins += reward > 0
    assert abs(wins / n - exact) < 4 * np.sqrt(exact * (1 - exact) / n)


def test_shortest_paths_reach_the_goal_and_the_decoy_is_off_them() -> None:
    paths = envs.shortest_paths()
    assert len(paths) >= 2 and len({len(p) for p in paths}) == 1
    env = envs.make_maze()
    for path in paths:
        env.reset()
        for i, a in enumerate(path):
            _, reward, terminated, _, info = env.step(a)
            assert terminated == (i == len(path) - 1)
        assert reward == pytest.approx(envs.goal_return(len(path), envs.MAZE_CAP))
        assert info["is_success"]
        visited = {_walk(path[: i + 1]) for i in range(len(path))}
        assert envs.DECOY_CELL not in visited


def test_decoy_ends_the_episode_with_its_reward() -> None:
    env = envs.make_maze(decoy=True)
    env.reset()
    # (0,7) -> up (0,6) -> right (1,6) -> right (2,6) -> up (2,5): the decoy.
    for a, done in [(0, False), (3, False), (3, False), (0, True)]:
        _, reward, terminated, truncated, info = env.step(a)
        assert terminated == done and not truncated
    assert reward == envs.DECOY_REWARD and info["is_success"] is False


def test_sticky_actions_repeat_the_previous_action() -> None:
    env = envs.make_maze(sticky=0.25)
    env.reset(seed=3)
    repeated = 0
    trials = 2000
    for _ in range(trials):
        env.reset()
        env.step(3)  # right, from the start: (1, 7)
        _, _, _, _, _ = env.step(0)  # up: (1, 6) unless the right is repeated: (2, 7)
        repeated += env.unwrapped.pos == (2, 7)
    assert 0.2 < repeated / trials < 0.3


def test_doorkey_fixed_layout_repeats_and_procedural_does_not() -> None:
    pytest.importorskip("minigrid")
    fixed = gym.make("TamrmRegimes/DoorKey-v0", size=5, layout_seed=7)
    first, _ = fixed.reset(seed=123)
    again, _ = fixed.reset()
    assert np.array_equal(first, again) and first.shape == (147,)
    proc = gym.make("TamrmRegimes/DoorKey-v0", size=5)
    layouts = {proc.reset(seed=s)[0].tobytes() for s in range(8)}
    assert len(layouts) > 1


def test_grids_and_selection_rule() -> None:
    a = stage_a_grid()
    assert len(a) == 16 and len({config_id(c) for c in a}) == 16
    assert {c["alpha"] for c in a} == {0.03, 0.1, 0.3, 0.8}
    assert {c["require_score_spread"] for c in a} == {False, True}
    b = stage_b_grid(a[5])
    assert len(b) == 8 and all(c["alpha"] == a[5]["alpha"] for c in b)
    assert all(c["k"] <= c["pool_capacity"] and c["min_pool_size"] <= c["pool_capacity"] for c in b)
    assert len(sil_grid()) == 24  # SIL gets the shaping grid's budget
    scores = {config_id(a[0]): [1.0, 2.0], config_id(a[3]): [2.0, 1.0], config_id(a[2]): [0.0, 0.1]}
    assert select(scores, a) == a[0]  # a tie goes to the earlier setting
    scores[config_id(a[3])] = [2.0, 1.5]
    assert select(scores, a) == a[3]
    with pytest.raises(ValueError):
        select({}, a)


def test_variants() -> None:
    assert {v.family for v in VARIANTS.values()} == {"E1", "E2", "E3"}
    assert VARIANTS["E2-fixed"].env_kwargs(4)["layout_seed"] == 4
    assert "layout_seed" not in VARIANTS["E2-proc"].env_kwargs(4)


def test_sil_learns_only_from_what_beat_the_critic() -> None:
    """SIL's buffer returns are the discounted returns; a buffer whose returns are below
    every value estimate makes no update."""
    pytest.importorskip("stable_baselines3")
    import torch

    from tamrm_regimes.sil import SilPPO, _SilBuffer

    buffer = _SilBuffer(capacity=5, gamma=0.5)
    buffer.add_episode([(np.zeros(2), 0, 0.0), (np.zeros(2), 1, 0.0), (np.zeros(2), 0, 4.0)])
    assert buffer.returns == [1.0, 2.0, 4.0]
    buffer.add_episode([(np.ones(2), 1, 1.0)] * 3)
    assert len(buffer) == 5 and buffer.returns[-1] == 1.0  # the oldest were dropped

    model = SilPPO("MlpPolicy", "CartPole-v1", n_steps=64, batch_size=32, seed=0, device="cpu")
    model._sil_buffer.add_episode([(np.zeros(4, dtype=np.float32), 0, -100.0)] * 4)
    before = [p.detach().clone() for p in model.policy.parameters()]
    model._sil_train()
    assert all(torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
    model._sil_buffer.add_episode([(np.zeros(4, dtype=np.float32), 1, 100.0)] * 4)
    model._sil_train()
    assert not all(
        torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True)
    )
