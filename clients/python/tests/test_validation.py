"""Hypothesis tests of the array shapes and dtypes a session step accepts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import tamrm
from tamrm._batch import PreparedBatch, StepInput
from tamrm._batch import prepare_batch as _prepare_batch

INT_DTYPES = st.sampled_from([np.int64, np.int32, np.int16, np.uint8, np.uint32, np.uint64])
REAL_DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.int32])


def prepare_batch(
    config: tamrm.TaskConfig, num_envs: int, *args: object, **kwargs: object
) -> PreparedBatch:
    """The step's arguments as ``Session.step`` takes them."""
    return _prepare_batch(config, num_envs, StepInput(*args, **kwargs))  # type: ignore[arg-type]


def discrete_config(n: int) -> tamrm.TaskConfig:
    return tamrm.TaskConfig(n, 0, 20, 20, 10, 20, 0.8, 0.8, 0.99, 100000)


def continuous_config(m: int) -> tamrm.TaskConfig:
    return tamrm.TaskConfig(0, m, 20, 20, 10, 20, 0.8, 0.8, 0.99, 100000)


@st.composite
def discrete_steps(draw: st.DrawFn) -> dict[str, object]:
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
def test_valid_discrete_batches_round_trip(step: dict, data: st.DataObject) -> None:
    n, b = step["n"], step["b"]
    use_q = data.draw(st.booleans())
    kwargs: dict[str, object] = {}
    if use_q:
        kwargs["q_values"] = data.draw(hnp.arrays(np.float64, (b, n), elements=st.floats(-10, 10)))
        kwargs["next_q_values"] = data.draw(
            hnp.arrays(np.float32, (b, n), elements=st.floats(-10, 10, width=32))
        )
    else:
        kwargs["values"] = data.draw(hnp.arrays(np.float64, b, elements=st.floats(-10, 10)))
        kwargs["next_values"] = data.draw(hnp.arrays(np.int64, b, elements=st.integers(-5, 5)))
    prepared = prepare_batch(
        discrete_config(n),
        b,
        step["actions"],
        step["rewards"],
        step["terminated"],
        step["truncated"],
        **kwargs,  # type: ignore[arg-type]
    )
    batch = prepared.request.steps
    assert prepared.request.WhichOneof("kind") == "steps"
    assert list(batch.env_ids) == []  # full batch: entry i is env i
    assert list(batch.actions) == np.asarray(step["actions"]).astype(np.int64).tolist()
    assert list(batch.rewards) == np.asarray(step["rewards"]).astype(np.float64).tolist()
    term, trunc = step["terminated"], step["truncated"]
    assert list(batch.terminated) in ([], term.tolist())
    assert list(batch.terminated) == (term.tolist() if term.any() else [])
    assert list(batch.truncated) == (trunc.tolist() if trunc.any() else [])
    assert prepared.done.tolist() == (term | trunc).tolist()
    if use_q:
        assert len(batch.q_values) == len(batch.next_q_values) == b * n
        np.testing.assert_array_equal(
            np.array(batch.q_values, np.float32),
            np.asarray(kwargs["q_values"]).astype(np.float32).ravel(),
        )
        assert len(batch.values) == 0
    else:
        assert len(batch.values) == len(batch.next_values) == b
        assert len(batch.q_values) == 0


@given(
    m=st.integers(1, 5),
    b=st.integers(1, 6),
    dtype=st.sampled_from([np.float64, np.float32, np.int64]),
    data=st.data(),
)
def test_valid_continuous_batches_are_row_major(
    m: int, b: int, dtype: type, data: st.DataObject
) -> None:
    actions = data.draw(hnp.arrays(dtype, (b, m), elements=st.integers(-50, 50)))
    prepared = prepare_batch(continuous_config(m), b, actions, np.zeros(b))
    batch = prepared.request.steps
    assert len(batch.actions) == 0
    np.testing.assert_array_equal(
        np.array(batch.action_vectors, np.float32).reshape(b, m), actions.astype(np.float32)
    )


def _other_shape(data: st.DataObject, good: tuple[int, ...]) -> tuple[int, ...]:
    shape = data.draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=6))
    if shape == good:
        shape = (*good, 1)
    return shape


@given(st.data())
def test_wrong_shapes_raise_value_error_naming_the_argument(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 4))
    b = data.draw(st.integers(1, 5))
    good = {
        "actions": np.zeros(b, np.int64),
        "rewards": np.zeros(b),
        "terminated": np.zeros(b, bool),
        "truncated": np.zeros(b, bool),
        "values": np.zeros(b),
        "next_values": np.zeros(b),
        "q_values": None,
        "next_q_values": None,
    }
    name = data.draw(
        st.sampled_from(
            [
                "actions",
                "rewards",
                "terminated",
                "truncated",
                "values",
                "next_values",
                "q_values",
                "next_q_values",
            ]
        )
    )
    if name.endswith("q_values"):
        good["values"] = good["next_values"] = None
        good["q_values"] = np.zeros((b, n))
        good["next_q_values"] = np.zeros((b, n))
        wrong = _other_shape(data, (b, n))
    else:
        wrong = _other_shape(data, (b,))
    dtype = good[name].dtype  # type: ignore[union-attr]
    good[name] = np.zeros(wrong, dtype=dtype)
    with pytest.raises(ValueError, match=name):
        prepare_batch(
            discrete_config(n),
            b,
            good["actions"],
            good["rewards"],
            good["terminated"],
            good["truncated"],
            values=good["values"],
            next_values=good["next_values"],
            q_values=good["q_values"],
            next_q_values=good["next_q_values"],
        )


@given(
    name=st.sampled_from(["actions", "rewards", "terminated", "values"]),
    bad=st.sampled_from(["float", "str", "complex", "object"]),
)
def test_wrong_dtypes_raise_type_error(name: str, bad: str) -> None:
    b = 3
    args = {
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
    with pytest.raises(TypeError, match=name):
        prepare_batch(
            discrete_config(2),
            b,
            args["actions"],
            args["rewards"],
            args["terminated"],
            values=args["values"],
            next_values=np.zeros(b),
        )


@given(st.integers(-(2**40), 2**40).filter(lambda a: not 0 <= a < 5))
def test_out_of_range_actions(action: int) -> None:
    with pytest.raises(ValueError, match="actions"):
        prepare_batch(discrete_config(5), 2, np.array([0, action], np.int64), np.zeros(2))


def test_pairs_and_exclusive_arguments() -> None:
    cfg = discrete_config(2)
    z = np.zeros(2)
    with pytest.raises(TypeError, match="next_values"):
        prepare_batch(cfg, 2, [0, 1], z, values=z)
    with pytest.raises(TypeError, match="q_values"):
        prepare_batch(cfg, 2, [0, 1], z, next_q_values=np.zeros((2, 2)))
    with pytest.raises(TypeError, match="not both"):
        prepare_batch(
            cfg,
            2,
            [0, 1],
            z,
            values=z,
            next_values=z,
            q_values=np.zeros((2, 2)),
            next_q_values=np.zeros((2, 2)),
        )
    with pytest.raises(ValueError, match="discrete"):
        prepare_batch(
            continuous_config(2),
            2,
            np.zeros((2, 2)),
            z,
            q_values=np.zeros((2, 2)),
            next_q_values=np.zeros((2, 2)),
        )
    with pytest.raises(ValueError, match="terminated"):
        prepare_batch(cfg, 2, [0, 1], z, terminated=np.array([0, 2]))
    with pytest.raises(ValueError, match="episode_scores"):
        prepare_batch(cfg, 2, [0, 1], z, episode_scores={2: 1.0})
    with pytest.raises(TypeError, match="episode_scores"):
        prepare_batch(cfg, 2, [0, 1], z, episode_scores={"0": 1.0})


def test_episode_scores_array_form() -> None:
    cfg = discrete_config(2)
    prepared = prepare_batch(
        cfg,
        4,
        [0, 1, 0, 1],
        np.zeros(4),
        terminated=[True, False, True, False],
        truncated=[False, False, False, True],
        episode_scores=np.array([5.0, 6.0, np.nan, 8.0]),
    )
    # Row 1 does not end an episode (ignored), row 2 has NaN (reward sum used).
    assert dict(prepared.request.steps.episode_scores) == {0: 5.0, 3: 8.0}


def test_session_rejects_before_sending(client: tamrm.Client, task_id: str) -> None:
    """Against the server: random wrong shapes/dtypes never reach it; good ones do."""
    client.create_task(task_id, num_actions=3)
    sent = {"entries": 0}
    with client.session(task_id, 4) as session:

        @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
        @given(
            actions_shape=st.sampled_from([(4,), (3,), (4, 1), (), (5,)]),
            actions_dtype=st.sampled_from([np.int64, np.int32, np.float64]),
            rewards_shape=st.sampled_from([(4,), (4, 1), (2,)]),
            rewards_dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_]),
        )
        def check(actions_shape, actions_dtype, rewards_shape, rewards_dtype) -> None:  # type: ignore[no-untyped-def]
            actions = np.ones(actions_shape, dtype=actions_dtype)
            rewards = np.ones(rewards_shape, dtype=rewards_dtype)
            ok = (
                actions_shape == (4,)
                and np.dtype(actions_dtype).kind == "i"
                and rewards_shape == (4,)
                and rewards_dtype is not np.bool_
            )
            if ok:
                result = session.step(actions, rewards)
                assert result.rewards.tolist() == [1.0] * 4
                sent["entries"] += 4
            else:
                with pytest.raises((ValueError, TypeError)):
                    session.step(actions, rewards)
            assert not session.closed

        check()
    assert client.get_task(task_id).stats.steps_shaped == sent["entries"]
