"""``gate_potential`` (SPEC v1.1 §1.1, §4): F counts only on steps where the kNN term is active."""

from __future__ import annotations

import asyncio
import math
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from reference import RefConfig, RefPool, RefStream

import tamrm
import tamrm.aio


def test_gated_potential_is_zero_where_knn_is_inactive(client: tamrm.Client, task_id: str) -> None:
    """One env, start_step 2, pool [0]*4: steps 0, 1 and 4+ inactive, 2 and 3 active."""
    for gate in (False, True):
        tid = f"{task_id}-{gate}"
        client.create_task(
            tid,
            num_actions=2,
            pool_capacity=1,
            min_pool_size=1,
            start_step=2,
            gamma=0.5,
            beta=2.0,
            gate_potential=gate,
        )
        client.add_trajectory(tid, [0, 0, 0, 0], 1.0)
        with client.session(tid, 1) as s:
            active, potentials, rewards = [], [], []
            for _ in range(6):
                res = s.step([0], [1.0], values=[1.0], next_values=[4.0])
                active.append(bool(res.knn_active[0]))
                potentials.append(float(res.potentials[0]))
                rewards.append(float(res.rewards[0]))
        assert active == [False, False, True, True, False, False]
        # F = 0.5 * 4 - 1 = 1, unless gated on an inactive step.
        want = [1.0 if (a or not gate) else 0.0 for a in active]
        assert potentials == want
        # Exact prefix match: r = e^1 - e^0.5 on active steps.
        knn = math.exp(1) - math.exp(0.5)
        want_r = [
            1.0 + 0.8 * (knn if a else 0.0) + 2.0 * f for a, f in zip(active, want, strict=True)
        ]
        assert rewards == pytest.approx(want_r, rel=1e-12)


def test_aio_create_task_gate_potential(server: tamrm.LocalServer, task_id: str) -> None:
    async def main() -> None:
        async with tamrm.aio.Client(server.address) as c:
            task = await c.create_task(task_id, num_actions=3, gate_potential=True)
            assert task.config.gate_potential is True
            assert (await c.get_task(task_id)).config.gate_potential is True
            async with c.session(task_id, 1) as s:
                assert s.config.gate_potential is True
                # Empty pool: kNN inactive, so the gated F is 0.
                res = await s.step([1], [0.5], values=[1.0], next_values=[3.0])
                assert res.potentials.tolist() == [0.0]
                assert res.rewards.tolist() == [0.5]

    asyncio.run(main())


# -- property: the server equals the naive reference, gated or not ------------------------
# (and with or without require_score_spread, SPEC v1.3, which decides where the kNN term,
# and so the gate, is active: the small integer scores make pools of equal scores common)


@st.composite
def scenarios(draw: st.DrawFn) -> dict[str, object]:
    num_actions = draw(st.integers(2, 3))
    capacity = draw(st.integers(1, 4))
    config = {
        "num_actions": num_actions,
        "pool_capacity": capacity,
        "k": draw(st.integers(1, capacity)),
        "min_pool_size": draw(st.integers(1, capacity)),
        "start_step": draw(st.integers(0, 3)),
        "alpha": draw(st.sampled_from([0.0, 0.8, 1.5])),
        "beta": draw(st.sampled_from([0.5, 1.0, 2.0])),
        "gamma": draw(st.sampled_from([0.0, 0.9, 1.0])),
        "max_trajectory_len": draw(st.integers(2, 12)),
        "gate_potential": draw(st.booleans()),
        "require_score_spread": draw(st.booleans()),
    }
    action = st.integers(0, num_actions - 1)
    seeds = draw(
        st.lists(
            st.tuples(st.lists(action, min_size=1, max_size=8), st.integers(-5, 5)),
            max_size=capacity,
        )
    )
    num_envs = draw(st.integers(1, 3))
    value = st.floats(-10, 10, width=32)
    row = st.tuples(action, st.integers(-3, 3), st.sampled_from(["", "", "", "term", "trunc"]))
    steps = draw(
        st.lists(
            st.tuples(
                st.lists(row, min_size=num_envs, max_size=num_envs),
                st.one_of(
                    st.none(),
                    st.lists(st.tuples(value, value), min_size=num_envs, max_size=num_envs),
                ),
            ),
            min_size=1,
            max_size=14,
        )
    )
    return {"config": config, "seeds": seeds, "num_envs": num_envs, "steps": steps}


@settings(max_examples=40, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scenario=scenarios())
def test_shaped_values_equal_reference(client: tamrm.Client, scenario: dict[str, object]) -> None:
    task_id = f"t/gate-prop/{uuid.uuid4().hex}"
    config = scenario["config"]
    assert isinstance(config, dict)
    task = client.create_task(task_id, **config)
    assert task.config.gate_potential is config["gate_potential"]
    assert task.config.require_score_spread is config["require_score_spread"]
    for actions, score in scenario["seeds"]:  # type: ignore[attr-defined]
        client.add_trajectory(task_id, np.array(actions, dtype=np.int64), float(score))
    cfg = RefConfig.of(task.config)
    ref = RefPool(cfg)
    ref.sync(client.get_pool(task_id))
    num_envs = int(scenario["num_envs"])  # type: ignore[call-overload]
    stream = RefStream(ref, num_envs)
    try:
        with client.session(task_id, num_envs) as session:
            for rows, values in scenario["steps"]:  # type: ignore[attr-defined]
                actions = np.array([r[0] for r in rows], dtype=np.int64)
                rewards = np.array([float(r[1]) for r in rows])
                terminated = np.array([r[2] == "term" for r in rows])
                truncated = np.array([r[2] == "trunc" for r in rows])
                kwargs = {}
                if values is not None:
                    kwargs = {
                        "values": np.array([v[0] for v in values]),
                        "next_values": np.array([v[1] for v in values]),
                    }
                res = session.step(actions, rewards, terminated, truncated, **kwargs)
                for env in range(num_envs):
                    if cfg.require_score_spread and len({t.score for t in ref.trajectories}) == 1:
                        event("a step on a pool of equal scores with require_score_spread")
                    want = stream.shape(
                        env,
                        int(actions[env]),
                        float(rewards[env]),
                        bool(terminated[env]),
                        bool(truncated[env]),
                        None if values is None else values[env][0],
                        None if values is None else values[env][1],
                    )
                    assert int(res.steps[env]) == want["step"]
                    assert bool(res.knn_active[env]) == want["knn_active"]
                    assert res.knn_rewards[env] == pytest.approx(
                        want["knn_reward"], rel=1e-9, abs=1e-12
                    )
                    # Values are sent as float32 and widened: the reference does the same.
                    assert res.potentials[env] == pytest.approx(
                        want["potential"], rel=1e-9, abs=1e-9
                    )
                    if cfg.gate_potential and not want["knn_active"]:
                        assert res.potentials[env] == 0.0
                    assert res.rewards[env] == pytest.approx(want["reward"], rel=1e-9, abs=1e-9)
                assert res.pool_version == ref.version
        pool = client.get_pool(task_id)
        assert [(t.actions.tolist(), t.score) for t in pool.trajectories] == [
            (np.asarray(t.actions).tolist(), t.score) for t in ref.trajectories
        ]
    finally:
        client.delete_task(task_id)
