import numpy as np
import pytest

from tamrm_experiments.envs import (
    MAZE_GOAL,
    MAZE_NEW_START,
    MAZE_START,
    MAZE_WALLS,
    MazeEnv,
    PaperCartPoleReward,
    make_cartpole,
    make_mountain_car,
    maze_shortest_path,
)

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def test_maze_layout():
    assert len(MAZE_WALLS) == 18
    assert MAZE_START not in MAZE_WALLS and MAZE_GOAL not in MAZE_WALLS
    assert maze_shortest_path(MAZE_START) > 0
    assert maze_shortest_path(MAZE_NEW_START) > 0
    assert MAZE_NEW_START != MAZE_START


def test_maze_edges_and_walls_block():
    env = MazeEnv()
    obs, _ = env.reset(seed=0)
    assert tuple(obs) == (0, 7)
    obs, r, term, trunc, _ = env.step(LEFT)  # off the grid
    assert tuple(obs) == (0, 7) and r == 0 and not term and not trunc
    obs, *_ = env.step(DOWN)  # off the grid
    assert tuple(obs) == (0, 7)
    obs, *_ = env.step(UP)
    assert tuple(obs) == (0, 6)
    obs, *_ = env.step(UP)  # (0,5) is a wall
    assert tuple(obs) == (0, 6)
    obs, *_ = env.step(RIGHT)
    obs, *_ = env.step(RIGHT)
    obs, *_ = env.step(RIGHT)
    assert tuple(obs) == (3, 6)
    obs, *_ = env.step(UP)  # (3,5) is a wall
    assert tuple(obs) == (3, 6)
    obs, *_ = env.step(DOWN)  # (3,7) is a wall
    assert tuple(obs) == (3, 6)
    assert env.steps == 9


def _bfs_actions(start):
    from collections import deque

    moves = {UP: (0, -1), DOWN: (0, 1), LEFT: (-1, 0), RIGHT: (1, 0)}
    prev = {start: None}
    q = deque([start])
    while q:
        cell = q.popleft()
        if cell == MAZE_GOAL:
            break
        for a, (dx, dy) in moves.items():
            nxt = (cell[0] + dx, cell[1] + dy)
            ok = 0 <= nxt[0] < 8 and 0 <= nxt[1] < 8 and nxt not in MAZE_WALLS
            if ok and nxt not in prev:
                prev[nxt] = (cell, a)
                q.append(nxt)
    actions = []
    cell = MAZE_GOAL
    while prev[cell] is not None:
        cell, a = prev[cell]
        actions.append(a)
    return actions[::-1]


def test_maze_goal_reward_and_score():
    env = MazeEnv()
    env.reset()
    actions = _bfs_actions(MAZE_START)
    assert len(actions) == maze_shortest_path(MAZE_START)
    for i, a in enumerate(actions):
        obs, r, term, trunc, info = env.step(a)
        if i < len(actions) - 1:
            assert r == 0 and not term and not trunc and "episode_score" not in info
    assert tuple(obs) == MAZE_GOAL
    assert r == 1.0 and term and not trunc
    assert info["is_success"] is True
    assert info["episode_score"] == pytest.approx(100 / len(actions))


def test_maze_truncates_at_cap_with_zero_score():
    env = MazeEnv(max_steps=25)
    env.reset()
    for i in range(25):
        _, r, term, trunc, info = env.step(LEFT)
        assert r == 0 and not term
        assert trunc == (i == 24)
    assert info == {"episode_score": 0.0, "is_success": False}


def test_modified_maze_moves_start_after_switch():
    env = MazeEnv(switch_start_after=2)
    starts = [tuple(env.reset()[0]) for _ in range(4)]
    assert starts == [MAZE_START, MAZE_START, MAZE_NEW_START, MAZE_NEW_START]


def test_cartpole_paper_reward():
    env = make_cartpole()
    assert isinstance(env, PaperCartPoleReward)
    env.reset(seed=1)
    rewards = []
    while True:
        _, r, term, trunc, _ = env.step(0)  # always push left: fails quickly
        rewards.append(r)
        if term or trunc:
            break
    assert term and not trunc
    assert rewards[:-1] == [1.0] * (len(rewards) - 1)
    assert rewards[-1] == -1.0


def test_cartpole_truncation_is_not_a_failure():
    env = make_cartpole()
    assert env.spec.max_episode_steps == 200

    class Stub:
        def step(self, _a):
            return np.zeros(4), 1.0, False, True, {}

    wrapper = PaperCartPoleReward(env)
    wrapper.env = Stub()
    assert wrapper.step(0)[1] == 1.0


def test_mountain_car_cap():
    env = make_mountain_car(max_steps=50)
    env.reset(seed=0)
    n = 0
    while True:
        _, r, term, trunc, _ = env.step(1)
        n += 1
        assert r == -1.0
        if term or trunc:
            break
    assert n == 50 and trunc and not term


def test_maze_random_walk_steps_matches_a_simulation():
    from tamrm_experiments.envs import maze_random_walk_steps

    exact = maze_random_walk_steps()
    rng = np.random.default_rng(0)
    env = MazeEnv(max_steps=100_000)
    lengths = []
    for _ in range(300):
        env.reset()
        n, done = 0, False
        while not done:
            _, _, done, _, _ = env.step(int(rng.integers(4)))
            n += 1
        lengths.append(n)
    # The walk's length has a standard deviation about equal to its mean: 300 walks give
    # the mean to within ~6% (1 sigma).
    assert abs(np.mean(lengths) - exact) < 0.2 * exact
    assert 700 < exact < 900


def test_the_vectorised_mountain_car_step_is_gymnasiums():
    from gymnasium.envs.classic_control.mountain_car import MountainCarEnv

    from tamrm_experiments.envs import _mountain_car_step

    env = MountainCarEnv()
    rng = np.random.default_rng(1)
    compared = 0
    for episode in range(5):
        env.reset(seed=episode)
        for _ in range(2000):
            position, velocity = (float(v) for v in env.state)
            action = int(rng.integers(3))
            env.step(action)
            vel, pos = _mountain_car_step(
                np.array([position]), np.array([velocity]), np.array([action])
            )
            assert (pos[0], vel[0]) == pytest.approx(tuple(float(v) for v in env.state), abs=1e-12)
            compared += 1
    assert compared == 10_000


def test_random_policy_references():
    from tamrm_experiments.envs import (
        maze_random_walk_steps,
        mountain_car_random_steps,
        random_policy_steps,
    )

    # Cart pole: a random policy drops the pole after ~22 steps (the well-known figure).
    assert 18 < random_policy_steps("cartpole", 200) < 26
    # Mountain car: a random policy rarely reaches the flag; a tighter cap cuts more.
    capped = mountain_car_random_steps(1_000, episodes=300)
    assert capped.max() == 1_000 and 0.5 < (capped == 1_000).mean() < 1.0
    looser = mountain_car_random_steps(10_000, episodes=300)
    assert np.all(looser >= capped) and looser.mean() > capped.mean()
    assert random_policy_steps("maze", 10_000) == maze_random_walk_steps()
    assert (
        random_policy_steps("maze_modified", 10_000, after_switch=True) < maze_random_walk_steps()
    )
    with pytest.raises(ValueError, match="no random-policy reference"):
        random_policy_steps("pendulum", 200)
