"""``require_score_spread`` (SPEC v1.3 §1.1, §3): the kNN term only while the pool's
scores differ, through the Python client against the server and the embedded Engine.

The property test against the naive reference (``reference.py``) is in
``test_gate_potential.py``, whose scenarios draw this switch too; the local sessions'
bit-identity with it is in ``test_local_session.py``.
"""

from __future__ import annotations

import math

import numpy as np

import tamrm

#: An exact prefix match on a pool whose scores are all equal (every x = 1): f = 1.
FLAT_BONUS = math.exp(1.0) - math.exp(0.5)


def spread_config(require_score_spread: bool | None) -> tamrm.TaskOptions:
    """A discrete task whose kNN term is active from the first step on a pool of one,
    with the potential gated and F = 0.5 * 4 - 1 = 1 for the values ``step`` sends."""
    return {
        "num_actions": 2,
        "pool_capacity": 3,
        "k": 3,
        "start_step": 0,
        "min_pool_size": 1,
        "beta": 1.0,
        "gamma": 0.5,
        "gate_potential": True,
        "require_score_spread": require_score_spread,
    }


def step(session: tamrm.Session, action: int, end_score: float | None = None) -> tamrm.StepResult:
    """One step of env 0 with R = 0, V(s) = 1, V(s') = 4; ``end_score`` truncates the
    episode with that score."""
    return session.step(
        [action],
        [0.0],
        truncated=[end_score is not None],
        values=[1.0],
        next_values=[4.0],
        episode_scores=None if end_score is None else {0: end_score},
    )


def test_equal_scores_pay_no_flat_bonus(client: tamrm.Client, task_id: str) -> None:
    """Two stored episodes of equal score: the paper's rule pays about 1.07 alpha per step
    whatever the actions; with the switch the kNN term (and the gated F) waits until an
    episode of another score is stored, and from then on both tasks shape alike."""
    paper, flat = f"{task_id}/paper", f"{task_id}/flat"
    assert client.create_task(paper, **spread_config(None)).config.require_score_spread is False
    assert client.create_task(flat, **spread_config(True)).config.require_score_spread is True
    for tid in (paper, flat):
        client.add_trajectory(tid, [0, 0, 0, 0], 1.0)
        client.add_trajectory(tid, [1, 1, 1, 1], 1.0)
    with client.session(paper, 1) as p, client.session(flat, 1) as f:
        assert f.config.require_score_spread is True
        for end in (None, 3.0):  # the ending step is shaped before its episode is stored
            got = step(p, 0, end)
            assert got.knn_active.tolist() == [True]
            assert got.knn_rewards.tolist() == [FLAT_BONUS]
            assert got.rewards.tolist() == [0.8 * FLAT_BONUS + 1.0]
            got = step(f, 0, end)
            assert got.knn_active.tolist() == [False]
            assert got.knn_rewards.tolist() == [0.0]
            assert got.potentials.tolist() == [0.0]
            assert got.rewards.tolist() == [0.0]
        for tid in (paper, flat):
            stats = client.get_task(tid).stats
            assert (stats.pool_size, stats.worst_score, stats.best_score) == (3, 1.0, 3.0)
        # Following [1, 1, 1, 1], whose x is 0 now: f = 0, r = 1 - e^0.5; the stored
        # [0, 0] ends the kNN term at t = 2 (L_min).
        for t in range(3):
            got, want = step(f, 1), step(p, 1)
            for name in ("rewards", "knn_rewards", "potentials", "knn_active"):
                assert np.array_equal(getattr(got, name), getattr(want, name)), (t, name)
            assert got.knn_active.tolist() == [t < 2]
            assert got.knn_rewards.tolist() == [1.0 - math.exp(0.5) if t < 2 else 0.0]
