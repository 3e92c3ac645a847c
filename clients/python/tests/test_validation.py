"""The array shapes and dtypes ``Session.step`` accepts, and what it does with the rest.

Every test goes through the real path: ``Session.step`` checks the arguments in Python and
hands them to the native extension. The hypothesis tests run on an in-process
``tamrm.Engine`` (fast); the others run on both a server and the engine (``client``).
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from reference import RefConfig, RefPool, RefStream

import tamrm

INT_DTYPES = st.sampled_from([np.int64, np.int32, np.int16, np.uint8, np.uint32, np.uint64])
REAL_DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.int32])


@contextmanager
def fresh_session(engine: tamrm.Engine, num_envs: int, **config: Any) -> Iterator[tamrm.Session]:
    """A session on a new task of ``engine`` (deleted afterwards)."""
    task_id = f"t/validation/{uuid.uuid4().hex}"
    engine.create_task(task_id, **config)
    try:
        with engine.session(task_id, num_envs) as session:
            yield session
    finally:
        engine.delete_task(task_id)


def assert_rejected(
    session: tamrm.Session, error: type[Exception], match: str, *args: Any, **kwargs: Any
) -> None:
    """``session.step(*args, **kwargs)`` raises ``error`` and leaves the session as it was."""
    before = session.episode_steps.copy()
    with pytest.raises(error, match=match):
        session.step(*args, **kwargs)
    assert not session.closed
    np.testing.assert_array_equal(session.episode_steps, before)


@st.composite
def discrete_steps(draw: st.DrawFn) -> dict[str, Any]:
    n = draw(st.integers(1, 6))
    b = draw(st.integers(1, 8))
    actions = draw(hnp.arrays(draw(INT_DTYPES), b, elements=st.integers(0, n - 1)))
    rewards = draw(
        hnp.arrays(draw(REAL_DTYPES), b, elements=st.integers(-100, 100))
        | hnp.arrays(np.float64, b, elements=st.floats(-1e6, 1e6))
    )
    terminated = draw(hnp.arrays(np.bool_, b))
    truncated = draw(hnp.arrays(np.bool_, b))
    return {
        "n": n,
        "b": b,
        "actions": actions,
        "rewards": rewards,
        "terminated": terminated,
        "truncated": truncated,
    }


@given(discrete_steps(), st.data())
def test_valid_discrete_batches_are_answered(
    engine: tamrm.Engine, step: dict[str, Any], data: st.DataObject
) -> None:
    n, b = step["n"], step["b"]
    num_envs = data.draw(st.integers(b, b + 3))
    kwargs: dict[str, Any] = {}
    if num_envs > b or data.draw(st.booleans()):
        # A subset of the environments, in any order, as any integer dtype.
        ids = np.array(data.draw(st.permutations(range(num_envs)))[:b])
        kwargs["env_ids"] = ids.astype(data.draw(INT_DTYPES))
    else:
        ids = np.arange(b)  # full batch: row i is env i
    use_q = data.draw(st.booleans())
    if use_q:
        q = data.draw(hnp.arrays(np.float64, (b, n), elements=st.floats(-10, 10)))
        nq = data.draw(hnp.arrays(np.float32, (b, n), elements=st.floats(-10, 10, width=32)))
        kwargs["q_values"], kwargs["next_q_values"] = q, nq
        # V = max_a Q, of the float32 values sent.
        values = q.astype(np.float32).max(axis=1).tolist()
        next_values = nq.max(axis=1).tolist()
    else:
        v = data.draw(hnp.arrays(np.float64, b, elements=st.floats(-10, 10)))
        nv = data.draw(hnp.arrays(np.int64, b, elements=st.integers(-5, 5)))
        kwargs["values"], kwargs["next_values"] = v, nv
        values, next_values = v.tolist(), nv.tolist()
    actions, rewards = step["actions"], step["rewards"]
    term, trunc = step["terminated"], step["truncated"]

    with fresh_session(engine, num_envs, num_actions=n) as session:
        result = session.step(actions, rewards, term, trunc, **kwargs)
        cfg = RefConfig.of(session.config)
        ref = RefPool(cfg)
        stream = RefStream(ref, num_envs)
        assert len(result) == b
        assert result.env_ids.dtype == np.int64
        assert result.env_ids.tolist() == ids.tolist()
        for row, env in enumerate(ids.tolist()):
            want = stream.shape(
                env,
                int(actions[row]),
                float(rewards[row]),
                bool(term[row]),
                bool(trunc[row]),
                values[row],
                next_values[row],
            )
            assert result.steps[row] == want["step"] == 0
            assert not result.knn_active[row]
            assert result.potentials[row] == pytest.approx(want["potential"], rel=1e-6, abs=1e-6)
            assert result.rewards[row] == pytest.approx(want["reward"], rel=1e-6, abs=1e-6)
        # The rows that ended an episode were offered to the pool (score: reward sum),
        # the others' episodes go on.
        pool = engine.get_pool(session.task_id)
        got = [(t.actions.tolist(), t.score) for t in pool.trajectories]
        assert got == [(t.actions.tolist(), t.score) for t in ref.trajectories]
        steps = np.zeros(num_envs, np.int64)
        steps[ids] = ~(term | trunc)
        np.testing.assert_array_equal(session.episode_steps, steps)


@given(
    m=st.integers(1, 5),
    b=st.integers(1, 6),
    dtype=st.sampled_from([np.float64, np.float32, np.int64]),
    data=st.data(),
)
def test_valid_continuous_batches_are_row_major(
    engine: tamrm.Engine, m: int, b: int, dtype: type, data: st.DataObject
) -> None:
    actions = data.draw(hnp.arrays(dtype, (b, m), elements=st.integers(-50, 50)))
    config = {"action_dim": m, "pool_capacity": 2, "k": 2, "min_pool_size": 2, "start_step": 0}
    with fresh_session(engine, b, **config) as session:
        # Two stored one-step trajectories, not symmetric in the coordinates: the kNN
        # reward of a row depends on which action vector reached which env.
        engine.add_trajectory(session.task_id, np.zeros((1, m)), 0.0)
        engine.add_trajectory(session.task_id, 10.0 * np.arange(1, m + 1)[None], 1.0)
        ref = RefPool(RefConfig.of(session.config))
        ref.sync(engine.get_pool(session.task_id))
        stream = RefStream(ref, b)
        result = session.step(actions, np.zeros(b))
        assert len(result) == b
        assert result.env_ids.tolist() == list(range(b))
        assert result.knn_active.all()
        for env in range(b):
            want = stream.shape(env, actions[env].astype(np.float32), 0.0)
            assert result.knn_rewards[env] == pytest.approx(want["knn_reward"], rel=1e-9, abs=1e-12)


def _other_shape(data: st.DataObject, good: tuple[int, ...]) -> tuple[int, ...]:
    shape = data.draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=6))
    if shape == good:
        shape = (*good, 1)
    return shape


@given(st.data())
def test_wrong_shapes_raise_value_error_naming_the_argument(
    engine: tamrm.Engine, data: st.DataObject
) -> None:
    n = data.draw(st.integers(1, 4))
    b = data.draw(st.integers(1, 5))
    good: dict[str, Any] = {
        "actions": np.zeros(b, np.int64),
        "rewards": np.zeros(b),
        "terminated": np.zeros(b, bool),
        "truncated": np.zeros(b, bool),
        "values": np.zeros(b),
        "next_values": np.zeros(b),
        "q_values": None,
        "next_q_values": None,
    }
    name = data.draw(st.sampled_from(sorted(good)))
    if name.endswith("q_values"):
        good["values"] = good["next_values"] = None
        good["q_values"] = np.zeros((b, n))
        good["next_q_values"] = np.zeros((b, n))
        wrong = _other_shape(data, (b, n))
    else:
        wrong = _other_shape(data, (b,))
    good[name] = np.zeros(wrong, dtype=good[name].dtype)
    actions, rewards = good.pop("actions"), good.pop("rewards")
    with fresh_session(engine, b, num_actions=n) as session:
        assert_rejected(session, ValueError, name, actions, rewards, **good)


@given(
    name=st.sampled_from(["actions", "rewards", "terminated", "values"]),
    bad=st.sampled_from(["float", "str", "complex", "object"]),
)
def test_wrong_dtypes_raise_type_error(engine: tamrm.Engine, name: str, bad: str) -> None:
    b = 3
    args: dict[str, Any] = {
        "actions": np.zeros(b, np.int64),
        "rewards": np.zeros(b),
        "terminated": np.zeros(b, bool),
        "values": np.zeros(b),
    }
    wrong = {
        "float": np.full(b, 0.5),
        "str": np.array(["a"] * b),
        "complex": np.zeros(b, np.complex128),
        "object": np.array([None] * b, dtype=object),
    }[bad]
    if name in ("rewards", "values") and bad == "float":
        return  # floats are the right dtype there
    if name == "terminated" and bad == "float":
        wrong = np.full(b, 1.0)
    args[name] = wrong
    with fresh_session(engine, b, num_actions=2) as session:
        assert_rejected(
            session,
            TypeError,
            name,
            args["actions"],
            args["rewards"],
            args["terminated"],
            values=args["values"],
            next_values=np.zeros(b),
        )


@given(st.integers(-(2**40), 2**40).filter(lambda a: not 0 <= a < 5))
def test_out_of_range_actions(engine: tamrm.Engine, action: int) -> None:
    with fresh_session(engine, 2, num_actions=5) as session:
        assert_rejected(
            session, ValueError, "actions", np.array([0, action], np.int64), np.zeros(2)
        )


def test_pairs_and_exclusive_arguments(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=2)
    client.create_task(f"{task_id}-c", action_dim=2)
    z = np.zeros(2)
    q = np.zeros((2, 2))
    with client.session(task_id, 2) as s:
        assert_rejected(s, TypeError, "next_values", [0, 1], z, values=z)
        assert_rejected(s, TypeError, "values", [0, 1], z, next_values=z)
        assert_rejected(s, TypeError, "q_values", [0, 1], z, next_q_values=q)
        assert_rejected(s, TypeError, "next_q_values", [0, 1], z, q_values=q)
        assert_rejected(
            s,
            TypeError,
            "not both",
            [0, 1],
            z,
            values=z,
            next_values=z,
            q_values=q,
            next_q_values=q,
        )
        assert_rejected(s, TypeError, "not both", [0, 1], z, values=z, next_values=z, q_values=q)
        assert_rejected(s, ValueError, "terminated", [0, 1], z, terminated=np.array([0, 2]))
        assert_rejected(s, ValueError, "episode_scores", [0, 1], z, episode_scores={2: 1.0})
        assert_rejected(s, TypeError, "episode_scores", [0, 1], z, episode_scores={"0": 1.0})
        # Nothing was sent: the episodes start now.
        assert s.step([0, 1], z).steps.tolist() == [0, 0]
    with client.session(f"{task_id}-c", 2) as s:
        assert_rejected(s, ValueError, "discrete", q, z, q_values=q, next_q_values=q)
        assert s.step(q, z).steps.tolist() == [0, 0]
    assert client.get_task(task_id).stats.steps_shaped == 2
    assert client.get_task(f"{task_id}-c").stats.steps_shaped == 2


def test_episode_scores_array_form(client: tamrm.Client, task_id: str) -> None:
    client.create_task(task_id, num_actions=4)
    with client.session(task_id, 4) as s:
        s.step(
            [0, 1, 2, 3],
            [1.0, 2.0, 3.0, 4.0],
            terminated=[True, False, True, False],
            truncated=[False, False, False, True],
            episode_scores=np.array([5.0, 6.0, math.nan, 8.0]),
        )
        # Row 1 does not end an episode (its score is ignored, it goes on); row 2 has NaN
        # (the reward sum is used).
        assert s.episode_steps.tolist() == [0, 1, 0, 0]
        stored = {tuple(t.actions.tolist()): t.score for t in client.get_pool(task_id).trajectories}
        assert stored == {(0,): 5.0, (2,): 3.0, (3,): 8.0}
        # Env 1's episode ends without a score: its reward sum, not the ignored 6.0.
        s.step([1], [10.0], terminated=[True], env_ids=[1])
        stored = {tuple(t.actions.tolist()): t.score for t in client.get_pool(task_id).trajectories}
        assert stored[(1, 1)] == 12.0


def test_session_rejects_before_sending(client: tamrm.Client, task_id: str) -> None:
    """Random wrong arguments never reach the server (or the engine); good ones do."""
    client.create_task(task_id, num_actions=3)
    sent = {"entries": 0}
    q = np.zeros((4, 3))
    with client.session(task_id, 4) as session:

        @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
        @given(
            actions_shape=st.sampled_from([(4,), (3,), (4, 1), (), (5,)]),
            actions_dtype=st.sampled_from([np.int64, np.int32, np.float64]),
            actions_value=st.sampled_from([1, 2, 3, -1]),
            rewards_shape=st.sampled_from([(4,), (4, 1), (2,)]),
            rewards_dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_]),
            extra=st.sampled_from(
                [
                    ({}, True),
                    ({"terminated": np.zeros(4, bool)}, True),
                    ({"values": np.zeros(4), "next_values": np.zeros(4)}, True),
                    ({"values": np.zeros(4)}, False),
                    ({"values": np.zeros(4), "next_values": np.zeros(4), "q_values": q}, False),
                    ({"env_ids": np.arange(1, 5)}, False),
                    ({"truncated": np.full(4, 2)}, False),
                ]
            ),
        )
        def check(  # type: ignore[no-untyped-def]
            actions_shape, actions_dtype, actions_value, rewards_shape, rewards_dtype, extra
        ) -> None:
            kwargs, valid = extra
            actions = np.full(actions_shape, actions_value, dtype=actions_dtype)
            rewards = np.ones(rewards_shape, dtype=rewards_dtype)
            ok = (
                actions_shape == (4,)
                and np.dtype(actions_dtype).kind == "i"
                and 0 <= actions_value < 3
                and rewards_shape == (4,)
                and rewards_dtype is not np.bool_
                and valid
            )
            before = session.episode_steps.copy()
            if ok:
                result = session.step(actions, rewards, **kwargs)
                assert len(result) == 4
                assert result.rewards.tolist() == [1.0] * 4
                assert result.steps.tolist() == before.tolist()
                np.testing.assert_array_equal(session.episode_steps, before + 1)
                sent["entries"] += 4
            else:
                with pytest.raises((ValueError, TypeError)):
                    session.step(actions, rewards, **kwargs)
                np.testing.assert_array_equal(session.episode_steps, before)
                assert client.get_task(task_id).stats.steps_shaped == sent["entries"]
            assert not session.closed

        check()
        # Still usable: the episodes go on where the accepted steps left them.
        steps = session.episode_steps.copy()
        assert session.step(np.zeros(4, np.int64), np.zeros(4)).steps.tolist() == steps.tolist()
        sent["entries"] += 4
    assert client.get_task(task_id).stats.steps_shaped == sent["entries"]
