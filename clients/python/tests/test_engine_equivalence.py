"""``tamrm.Engine`` (in-process) and ``tamrm.Client`` (a real server) give the same answers.

The same random step sequences go to an Engine session and to a Client session on a
``tamrm serve`` process; every shaped column must be bit-identical (the same f64, not
approximately), and so must the pools and the task statistics afterwards.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from reference import assert_pools_identical, assert_tasks_identical

import tamrm
from tamrm import _native

RESULT_COLUMNS = ("rewards", "knn_rewards", "potentials", "steps", "knn_active", "env_ids")


def outcome(fn: Callable[[], object]) -> tuple[type[BaseException], str]:
    """The class and message of the exception ``fn()`` raises."""
    with pytest.raises(Exception) as info:
        fn()
    return type(info.value), str(info.value)


def assert_results_identical(got: tamrm.StepResult, want: tamrm.StepResult) -> None:
    for name in RESULT_COLUMNS:
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert np.array_equal(a, b), (name, a, b)
        if a.dtype == np.float64:
            # Bit for bit: -0.0 and 0.0 compare equal, their bytes do not.
            assert a.tobytes() == b.tobytes(), name
    assert got.pool_version == want.pool_version


# -- random scenarios -----------------------------------------------------------------


@dataclass
class Scenario:
    config: dict[str, Any]
    num_envs: int
    mode: str  # "values", "q" or "none"
    demos: int
    batches: int
    seed: int
    end_prob: float

    @property
    def discrete(self) -> bool:
        return "num_actions" in self.config


def _optional(draw: Callable[..., Any], strategy: st.SearchStrategy[Any]) -> Any:
    """A value of ``strategy``, or (one time in four) ``None``: the server's default."""
    return None if draw(st.integers(0, 3)) == 0 else draw(strategy)


@st.composite
def scenarios(draw: Callable[..., Any]) -> Scenario:
    discrete = draw(st.booleans())
    cap = draw(st.integers(1, 6))
    weights = st.floats(-3, 3, allow_nan=False, allow_infinity=False)
    config: dict[str, Any] = {
        "pool_capacity": cap,
        "k": _optional(draw, st.integers(1, cap)),
        "start_step": _optional(draw, st.integers(0, 4)),
        "min_pool_size": _optional(draw, st.integers(1, cap)),
        "alpha": _optional(draw, weights),
        "beta": _optional(draw, weights),
        "gamma": _optional(draw, st.floats(0, 1)),
        "max_trajectory_len": _optional(draw, st.integers(1, 14)),
        "gate_potential": _optional(draw, st.booleans()),
        "require_score_spread": _optional(draw, st.booleans()),
    }
    if discrete:
        config["num_actions"] = draw(st.integers(1, 4))
    else:
        config["action_dim"] = draw(st.integers(1, 3))
    modes = ["values", "q", "none"] if discrete else ["values", "none"]
    return Scenario(
        config=config,
        num_envs=draw(st.integers(1, 4)),
        mode=draw(st.sampled_from(modes)),
        demos=draw(st.integers(0, cap + 1)),
        batches=draw(st.integers(1, 45)) if draw(st.booleans()) else 45,
        seed=draw(st.integers(0, 2**32 - 1)),
        end_prob=draw(st.sampled_from([0.05, 0.15, 0.4])),
    )


def random_actions(rng: np.random.Generator, config: dict[str, Any], size: int) -> np.ndarray:
    if "num_actions" in config:
        return rng.integers(0, config["num_actions"], size=size)
    shape = (size, config["action_dim"])
    # Mostly a coarse grid (exact prefix matches, dis = 0), sometimes values that are not
    # exact in float32; sometimes sent as float32.
    grid = rng.integers(-2, 3, size=shape) * 0.5
    actions = np.where(rng.random(shape) < 0.2, rng.normal(size=shape), grid)
    return actions.astype(np.float32) if rng.random() < 0.3 else actions


def random_batch(
    rng: np.random.Generator, sc: Scenario, num_actions: int
) -> tuple[list[int], dict[str, Any]]:
    """(envs to abandon first, the keyword arguments of one ``Session.step``)."""
    n = sc.num_envs
    abandon: list[int] = []
    if rng.random() < 0.1:
        abandon = sorted(rng.choice(n, size=rng.integers(1, n + 1), replace=False).tolist())
    env_ids = None
    size = n
    if rng.random() < 0.35:  # a subset, in any order, an env possibly listed twice
        size = int(rng.integers(1, 2 * n + 1))
        env_ids = rng.integers(0, n, size=size)
    ends = rng.random(size) < sc.end_prob
    terminated = ends & (rng.random(size) < 0.5)
    truncated = ends & ~terminated
    rewards = rng.normal(size=size) * 3
    if rng.random() < 0.3:
        rewards = rewards.round(1)
    kwargs: dict[str, Any] = {
        "actions": random_actions(rng, sc.config, size),
        "rewards": rewards,
        "env_ids": env_ids,
    }
    # The end flags: arrays, or left out (None: all false) when no row ends its episode.
    if ends.any() or rng.random() < 0.5:
        kwargs["terminated"] = terminated
        kwargs["truncated"] = truncated
    if sc.mode == "values":
        dtype = np.float32 if rng.random() < 0.5 else np.float64
        kwargs["values"] = rng.normal(size=size).astype(dtype)
        kwargs["next_values"] = rng.normal(size=size).astype(dtype)
    elif sc.mode == "q":
        kwargs["q_values"] = rng.normal(size=(size, num_actions))
        kwargs["next_q_values"] = rng.normal(size=(size, num_actions))
    scored = ends & (rng.random(size) < 0.4)
    if scored.any():
        scores = rng.normal(2.0, 3.0, size=size)
        if rng.random() < 0.5:
            kwargs["episode_scores"] = np.where(scored, scores, np.nan)
        else:
            kwargs["episode_scores"] = {
                int(i): float(scores[i]) for i in np.flatnonzero(scored).tolist()
            }
    return abandon, kwargs


def seed_demo(rng: np.random.Generator, config: dict[str, Any]) -> tuple[np.ndarray, float]:
    length = int(rng.integers(1, 16))
    return random_actions(rng, config, length), float(rng.normal(2.0, 3.0))


def reject_alike(sessions: list[tamrm.Session], kwargs: dict[str, Any]) -> bool:
    """Send ``kwargs`` with a score on a row that does not end its episode: every session
    rejects it with the same error and stays open. False if every row ends its episode."""
    size = len(kwargs["rewards"])
    done = np.zeros(size, dtype=bool)
    for flag in ("terminated", "truncated"):
        if flag in kwargs:
            done |= kwargs[flag]
    if done.all():
        return False
    bad = {**kwargs, "episode_scores": {int(np.flatnonzero(~done)[0]): 1.0}}
    errors = [outcome(lambda s=s: s.step(**bad)) for s in sessions]
    assert errors[0][0] is tamrm.InvalidArgument, errors
    assert all(e == errors[0] for e in errors), errors
    assert not any(s.closed for s in sessions)
    return True


def run_scenario(backends: list[tamrm.Client | tamrm.Engine], sc: Scenario) -> dict[str, int]:
    """Feed ``sc`` identically to a session on each backend; all answers must be the same.

    Returns what the run went through (active kNN entries, pool version at the end).
    """
    seen = {"active": 0, "nonzero_knn": 0, "nonzero_potential": 0, "rejected": 0}
    task_id = f"prop/{uuid.uuid4().hex}"
    tasks = [b.create_task(task_id, **sc.config) for b in backends]
    for t in tasks[1:]:
        assert_tasks_identical(t, tasks[0])
    config = tasks[0].config
    rng = np.random.default_rng(sc.seed)
    for _ in range(sc.demos):
        actions, score = seed_demo(rng, sc.config)
        added = [b.add_trajectory(task_id, actions, score) for b in backends]
        assert all(a == added[0] for a in added), added
    sessions = [b.session(task_id, sc.num_envs) for b in backends]
    try:
        for s in sessions[1:]:
            assert_tasks_identical(s.task, sessions[0].task)
        for i in range(sc.batches):
            if rng.random() < 0.04:  # seed the pool while the sessions are open
                actions, score = seed_demo(rng, sc.config)
                added = [b.add_trajectory(task_id, actions, score) for b in backends]
                assert all(a == added[0] for a in added), added
            abandon, kwargs = random_batch(rng, sc, config.num_actions)
            if abandon:
                for s in sessions:
                    s.abandon(abandon)
            if rng.random() < 0.06 and reject_alike(sessions, kwargs):
                seen["rejected"] += 1
            results = [s.step(**kwargs) for s in sessions]
            for r in results[1:]:
                assert_results_identical(r, results[0])
            seen["active"] += int(results[0].knn_active.sum())
            seen["nonzero_knn"] += int(np.count_nonzero(results[0].knn_rewards))
            seen["nonzero_potential"] += int(np.count_nonzero(results[0].potentials))
            steps = [s.episode_steps for s in sessions]
            for st_ in steps[1:]:
                assert np.array_equal(st_, steps[0]), (i, steps)
    finally:
        for s in sessions:
            s.close()
    pools = [b.get_pool(task_id) for b in backends]
    for p in pools[1:]:
        assert_pools_identical(p, pools[0])
    final = [b.get_task(task_id) for b in backends]
    for t in final[1:]:
        assert_tasks_identical(t, final[0])
    assert final[0].stats.pool_size == len(pools[0])
    seen["pool_version"] = pools[0].pool_version
    return seen


@given(sc=scenarios())
@settings(max_examples=150)
def test_engine_and_server_shape_bit_identically(
    engine: tamrm.Engine, remote_client: tamrm.Client, sc: Scenario
) -> None:
    seen = run_scenario([engine, remote_client], sc)
    # Shown by --hypothesis-show-statistics: how many examples reached each regime.
    event("kNN term active" if seen["active"] else "kNN term never active")
    event("pool changed" if seen["pool_version"] else "pool unchanged")


def test_the_property_test_reaches_active_knn_and_pool_changes(
    engine: tamrm.Engine, remote_client: tamrm.Client
) -> None:
    """The scenarios above are not vacuous: they shape with an active kNN term, store
    episodes (inserts and replacements), and the two backends still agree."""
    sc = Scenario(
        config={"num_actions": 2, "pool_capacity": 3, "start_step": 0, "k": 2},
        num_envs=3,
        mode="values",
        demos=3,
        batches=60,
        seed=5,
        end_prob=0.15,
    )
    seen = run_scenario([engine, remote_client], sc)
    assert seen["active"] > 20 and seen["nonzero_knn"] > 10, seen
    assert seen["nonzero_potential"] > 20, seen
    assert seen["pool_version"] > sc.demos + 2, seen
    assert seen["rejected"] >= 2, seen


# -- errors -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fresh_pair(server_binary: str) -> Iterator[tuple[tamrm.Engine, tamrm.Client]]:
    """An in-memory Engine and a server of its own: both hold exactly the same tasks."""
    with (
        tamrm.local_server(binary=server_binary, in_memory=True) as srv,
        tamrm.Client(srv.address) as client,
        tamrm.Engine() as engine,
    ):
        for b in (engine, client):
            b.create_task("cartpole-v1", num_actions=2, pool_capacity=4)
            b.create_task("pendulum", action_dim=2, pool_capacity=4)
        yield engine, client


Case = Callable[[Any], object]

ERROR_CASES: dict[str, tuple[type[BaseException], str, Case]] = {
    "get_task unknown": (
        tamrm.TaskNotFound,
        'did you mean "cartpole-v1"',
        lambda b: b.get_task("cartpole-v2"),
    ),
    "get_pool unknown": (tamrm.TaskNotFound, "pendulm", lambda b: b.get_pool("pendulm")),
    "delete unknown": (tamrm.TaskNotFound, "nope", lambda b: b.delete_task("nope")),
    "reset unknown": (tamrm.TaskNotFound, "cartpole", lambda b: b.reset_pool("cartpole")),
    "add_trajectory unknown": (
        tamrm.TaskNotFound,
        "cartpole-v",
        lambda b: b.add_trajectory("cartpole-v", [0, 1], 1.0),
    ),
    "session unknown": (tamrm.TaskNotFound, "Cartpole-v1", lambda b: b.session("Cartpole-v1")),
    "bad task id": (tamrm.InvalidArgument, "task", lambda b: b.create_task("a b", num_actions=2)),
    "too long task id": (
        tamrm.InvalidArgument,
        "task",
        lambda b: b.create_task("a" * 129, num_actions=2),
    ),
    "already exists": (
        tamrm.AlreadyExists,
        "pool_capacity",
        lambda b: b.create_task("cartpole-v1", num_actions=2, pool_capacity=5),
    ),
    "already exists, other kind": (
        tamrm.AlreadyExists,
        "cartpole-v1",
        lambda b: b.create_task("cartpole-v1", action_dim=2, pool_capacity=4),
    ),
    "add_trajectory empty": (
        tamrm.InvalidArgument,
        "trajectory.actions",
        lambda b: b.add_trajectory("cartpole-v1", np.zeros(0, np.int64), 1.0),
    ),
    "add_trajectory action out of range": (
        tamrm.InvalidArgument,
        "out of range",
        lambda b: b.add_trajectory("cartpole-v1", [0, 2], 1.0),
    ),
    "add_trajectory wrong vector length": (
        tamrm.InvalidArgument,
        "action_vectors",
        lambda b: b.add_trajectory("pendulum", np.zeros((3, 3)), 1.0),
    ),
    "config pool_capacity past the limit": (
        tamrm.ResourceExhausted,
        "max_pool_capacity",
        lambda b: b.create_task("x", num_actions=2, pool_capacity=10_001),
    ),
    "num_envs past the limit": (
        tamrm.ResourceExhausted,
        "num_envs",
        lambda b: b.session("cartpole-v1", 4097),
    ),
}


# Rejected configurations: (what the message names, the create_task keywords).
BAD_CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "k 0": ("config.k", dict(num_actions=2, k=0)),
    "k > capacity": ("config.k", dict(num_actions=2, pool_capacity=3, k=4)),
    "min_pool_size": ("min_pool_size", dict(num_actions=2, pool_capacity=3, min_pool_size=5)),
    "gamma": ("gamma", dict(num_actions=2, gamma=1.5)),
    "alpha nan": ("alpha", dict(num_actions=2, alpha=math.nan)),
    "both action kinds": ("action", dict(num_actions=2, action_dim=2)),
    "no action kind": ("action", {}),
    "max_trajectory_len": ("max_trajectory_len", dict(num_actions=2, max_trajectory_len=0)),
}
for _name, (_needle, _config) in BAD_CONFIGS.items():
    ERROR_CASES[f"config {_name}"] = (
        tamrm.InvalidArgument,
        _needle,
        lambda b, config=_config: b.create_task("x", **config),
    )


@pytest.mark.parametrize("name", list(ERROR_CASES))
def test_engine_errors_equal_the_servers(
    fresh_pair: tuple[tamrm.Engine, tamrm.Client], name: str
) -> None:
    cls, needle, call = ERROR_CASES[name]
    engine, client = fresh_pair
    got, want = outcome(lambda: call(engine)), outcome(lambda: call(client))
    assert got == want
    assert issubclass(got[0], cls), got
    assert needle in got[1], got
    # Nothing was created by a rejected call.
    assert [t.task_id for t in engine.list_tasks()] == ["cartpole-v1", "pendulum"]
    assert [t.task_id for t in client.list_tasks()] == ["cartpole-v1", "pendulum"]


def test_num_envs_zero_is_refused_alike(fresh_pair: tuple[tamrm.Engine, tamrm.Client]) -> None:
    engine, client = fresh_pair
    # The public call stops it before it is sent; the native transports, asked directly,
    # answer with the same status.
    public = [outcome(lambda b=b: b.session("cartpole-v1", 0)) for b in fresh_pair]
    assert public[0] == public[1] == (ValueError, "num_envs must be >= 1, got 0")
    answers = []
    for b in (engine, client):
        with pytest.raises(_native.StatusError) as info:
            b._transport.open("cartpole-v1", 0, "c")
        answers.append(info.value.args)
    assert answers[0] == answers[1]
    assert answers[0][0] == 3 and "num_envs" in answers[0][1], answers  # INVALID_ARGUMENT


def test_a_score_on_a_non_final_entry_is_refused_alike(
    fresh_pair: tuple[tamrm.Engine, tamrm.Client],
) -> None:
    outcomes = []
    for b in fresh_pair:
        with b.session("cartpole-v1", 2) as s:
            s.step([0, 1], [1.0, 1.0])
            bad = outcome(
                lambda s=s: s.step([0, 1], [1.0, 1.0], [True, False], episode_scores={1: 2.0})
            )
            assert not s.closed
            outcomes.append(bad)
    assert outcomes[0] == outcomes[1]
    assert outcomes[0][0] is tamrm.InvalidArgument and "episode_scores" in outcomes[0][1]


def test_a_task_deleted_under_a_session_fails_alike(
    fresh_pair: tuple[tamrm.Engine, tamrm.Client],
) -> None:
    outcomes = []
    for b in fresh_pair:
        b.create_task("doomed", num_actions=3)
        s = b.session("doomed", 1)
        s.step([2], [1.0])
        b.delete_task("doomed")
        first = outcome(lambda s=s: s.step([1], [1.0]))
        assert s.closed
        again = outcome(lambda s=s: s.step([1], [1.0]))
        s.close()
        outcomes.append((first, again, outcome(lambda b=b: b.get_task("doomed"))))
    assert outcomes[0] == outcomes[1]
    (first_cls, first_msg), (again_cls, _), (gone_cls, _) = outcomes[0]
    assert first_cls is tamrm.TaskNotFound and "doomed" in first_msg
    assert again_cls is tamrm.SessionClosed
    assert gone_cls is tamrm.TaskNotFound


# -- a rejected batch changes nothing ------------------------------------------------------


REJECTED_CONFIG: dict[str, Any] = dict(
    pool_capacity=4, k=2, start_step=1, min_pool_size=2, max_trajectory_len=5, alpha=0.7, beta=0.3
)


def _rejection_script(discrete: bool) -> list[dict[str, Any]]:
    rng = np.random.default_rng(11)
    out = []
    for t in range(24):
        actions = rng.integers(0, 3, 3) if discrete else rng.integers(-1, 2, (3, 2)) * 0.5
        out.append(
            {
                "actions": actions,
                # Not round: the default score (the reward sum) must survive a re-opened
                # stream exactly.
                "rewards": rng.normal(size=3) / 7,
                "terminated": np.array([t in (6, 15), t == 11, t == 20]),
                "truncated": np.array([False, False, t == 9]),
                "values": rng.normal(size=3),
                "next_values": rng.normal(size=3),
            }
        )
    return out


@pytest.mark.parametrize("discrete", [True, False], ids=["discrete", "continuous"])
def test_after_a_rejected_batch_results_stay_identical(
    engine: tamrm.Engine, remote_client: tamrm.Client, discrete: bool
) -> None:
    base = f"rejected/{uuid.uuid4().hex}"
    kind = {"num_actions": 3} if discrete else {"action_dim": 2}
    demo = np.array([0, 1, 2, 1, 0, 2, 2]) if discrete else np.ones((7, 2)) / 2
    # (backend, task, whether the session sends bad batches)
    runs = []
    for b in (engine, remote_client):
        for hurt in (False, True):
            tid = f"{base}/{'hurt' if hurt else 'clean'}"
            b.create_task(tid, **kind, **REJECTED_CONFIG)
            b.add_trajectory(tid, demo, 1.0)
            b.add_trajectory(tid, demo[:6], 2.0)
            runs.append((b, tid, hurt, b.session(tid, 3)))
    rejected = 0
    try:
        for t, step in enumerate(_rejection_script(discrete)):
            if t == 13:  # env 2 abandoned; the abandon is pending when the bad batch goes
                for _, _, _, s in runs:
                    s.abandon([2])
            results = []
            for _, _, hurt, s in runs:
                if hurt and t in (3, 8, 13, 21):
                    # Mid-episode on env 1 (and past max_trajectory_len at t=8): a score
                    # on an entry that does not end an episode.
                    with pytest.raises(tamrm.InvalidArgument, match="episode_scores"):
                        s.step(**step, episode_scores={1: 5.0, 0: 1.0})
                    assert not s.closed
                    rejected += 1
                results.append(s.step(**step))
            for r in results[1:]:
                assert_results_identical(r, results[0])
            steps = [s.episode_steps for _, _, _, s in runs]
            assert all(np.array_equal(x, steps[0]) for x in steps), (t, steps)
    finally:
        for _, _, _, s in runs:
            s.close()
    assert rejected == 8
    pools = [b.get_pool(tid) for b, tid, _, _ in runs]
    tasks = [b.get_task(tid) for b, tid, _, _ in runs]
    # 2 demonstrations + 5 episode ends (and env 2's abandoned one), on a pool of 4.
    assert pools[0].pool_version > 4
    for p, t in zip(pools[1:], tasks[1:], strict=True):
        assert p.pool_version == pools[0].pool_version
        assert [(x.seq, x.score) for x in p.trajectories] == [
            (x.seq, x.score) for x in pools[0].trajectories
        ]
        for x, y in zip(p.trajectories, pools[0].trajectories, strict=True):
            assert np.array_equal(x.actions, y.actions)
        assert t.stats.steps_shaped == tasks[0].stats.steps_shaped == 24 * 3
        assert t.stats.episodes_completed == tasks[0].stats.episodes_completed == 5
        assert t.stats.open_streams == 0
