"""Our r(t) against the authors' own formula.

The authors compute the kNN reward in ``predict_modified`` (``Carpole_test/carpole.py``
and ``MountainCar_test/knn_reward_model.py`` of their published code; ``predict`` in the
maze, the same without the top-k step). :func:`authors_predict_modified` below is a
faithful transcription: the pool is a list of trajectories, each the one-hot actions
followed by the episode score; ``step_nums`` is t and ``data`` the current episode's
one-hot actions a'_0..a'_t.

Their formula and SPEC §3 (which tamrm implements) differ only by their epsilons:

1. ``+ 0.001`` on every component of ``e(a_j) - e(a'_j)`` before squaring, so
   ``dis_i`` never reaches 0: an exact match gets a large but finite weight (its
   distance is ``(t + 1) n 1e-6``) instead of SPEC's limit (the exact matches share
   P = 1 equally, the others get 0); every other distance changes by less than 0.1%.
2. ``+ 1e-8`` in the numerator and denominator of the score normalisation
   ``x_i = (S_i - S_min + 1e-8) / (S_max - S_min + 1e-8)``: negligible unless all scores
   are equal, where theirs gives x_i = 1 as SPEC does.
3. ``round(f, 4)``: f(t) rounded to 4 decimals before ``exp(f) - exp(0.5)``.
4. Their top-k keeps the first 20 (hard-coded) by P with ties broken by position in
   their list (``np.argmax``); SPEC breaks ties by score, then insertion order. With
   distinct P the two agree.

So the two agree to within a few 1e-3 (the tests: 3e-3), whether or not a stored prefix
matches exactly, and to 1e-6 once their epsilon is shrunk to 1e-7 and the rounding
dropped. The tests feed the same pools and prefixes to both, ours through a real local
server and the Python client.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

tamrm = pytest.importorskip("tamrm")


def onehot(a: int, n: int) -> list[int]:
    out = [0] * n
    out[a] = 1
    return out


def authors_predict_modified(memory, step_nums, data, k=20, eps=0.001, digits=4):
    """Transcription of their ``KNN_Predict.predict_modified`` (``k`` = their literal 20,
    ``eps`` = their 0.001, ``digits`` = their rounding; parameters only so the test can
    shrink them)."""
    memory_step = []
    memory_reward = []
    for x in memory:
        memory_reward.append(x[-1])
        memory_step.append(np.array(x[: step_nums + 1]) - np.array(data) + eps)
    distance = np.array(memory_step) ** 2
    distance = distance.sum(2)
    distance = distance.sum(1)
    distance = distance / distance.sum()
    dis_step = 1 / distance
    dis_step = dis_step / dis_step.sum()

    min_reward = np.min(memory_reward)
    max_reward = np.max(memory_reward)
    close_reward = []
    close_record = []
    for _ in range(k):
        index = np.argmax(dis_step)
        close_reward.append(memory_reward[index])
        close_record.append(dis_step[index])
        dis_step[index] = -1

    r_step = (np.array(close_reward) - min_reward + 1e-8) / (max_reward - min_reward + 1e-8)
    close_record = np.array(close_record).reshape(k, 1)
    res = np.dot(r_step, close_record)
    res = round(res[0], digits) if digits is not None else res[0]
    return np.exp(res) - np.exp(0.5)


def _pool(rng, size, n_actions, length):
    trajs = [rng.integers(n_actions, size=length).tolist() for _ in range(size)]
    scores = rng.permutation(size).astype(float) * 3.0 + 1.0  # distinct scores
    return trajs, scores


def _server_rewards(trajs, scores, prefix, n_actions, k, start_step=0):
    """r(t) for every step of ``prefix`` from a real tamrm server (pool seeded with
    AddTrajectory, the kNN term active from step 0)."""
    with tamrm.local_server() as server, tamrm.Client(server.address) as client:
        client.create_task(
            "t",
            num_actions=n_actions,
            pool_capacity=len(trajs),
            k=k,
            start_step=start_step,
            min_pool_size=len(trajs),
            alpha=1.0,
            beta=0.0,
        )
        for actions, score in zip(trajs, scores, strict=True):
            client.add_trajectory("t", np.array(actions), float(score))
        out = []
        with client.session("t", 1) as session:
            for a in prefix:
                res = session.step([a], [0.0])
                out.append((bool(res.knn_active[0]), float(res.knn_rewards[0])))
        return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_our_r_equals_theirs_up_to_their_epsilons(seed):
    rng = np.random.default_rng(seed)
    n_actions, size, k, length = 3, 20, 20, 30
    trajs, scores = _pool(rng, size, n_actions, length)
    # A prefix that follows the best trajectory for 5 steps, then wanders: exact matches
    # first (SPEC: P = 1 on it), then none.
    best = int(np.argmax(scores))
    prefix = trajs[best][:5] + rng.integers(n_actions, size=length - 5).tolist()
    ours = _server_rewards(trajs, scores, prefix, n_actions, k)
    memory = [[onehot(a, n_actions) for a in t] + [s] for t, s in zip(trajs, scores, strict=True)]
    data = []
    for t, a in enumerate(prefix):
        data.append(onehot(a, n_actions))
        active, r_ours = ours[t]
        assert active
        r_theirs = authors_predict_modified(memory, t, data, k=k)
        # Documented differences: eps 0.001 in the distances (at most ~0.2% of a
        # distance, and a finite weight for exact matches) and rounding to 4 decimals.
        assert r_ours == pytest.approx(r_theirs, abs=3e-3), (t, r_ours, r_theirs)
        # Without their epsilon and rounding the difference vanishes (no exact match) or
        # shrinks with the epsilon (an exact match: their weight tends to SPEC's limit).
        r_exact = authors_predict_modified(memory, t, data, k=k, eps=1e-7, digits=None)
        assert r_ours == pytest.approx(r_exact, abs=1e-6), (t, r_ours, r_exact)


def test_exact_match_rule_is_the_limit_of_their_epsilon():
    rng = np.random.default_rng(7)
    trajs, scores = _pool(rng, 5, 2, 12)
    prefix = trajs[int(np.argmin(scores))][:12]  # follows the worst trajectory exactly
    ours = _server_rewards(trajs, scores, prefix, 2, k=5)
    memory = [[onehot(a, 2) for a in t] + [s] for t, s in zip(trajs, scores, strict=True)]
    data = [onehot(a, 2) for a in prefix]
    _, r_ours = ours[-1]
    # SPEC: P = 1 on the exact match, whose normalised score is 0: r = exp(0) - exp(0.5).
    assert r_ours == pytest.approx(1 - math.exp(0.5), abs=1e-9)
    errs = [
        abs(authors_predict_modified(memory, 11, data, k=5, eps=e, digits=None) - r_ours)
        for e in (1e-2, 1e-3, 1e-4)
    ]
    assert errs[0] > errs[1] > errs[2]
    assert errs[1] < 1e-2  # their eps = 0.001


def test_their_top_k_keeps_the_largest_weights():
    # With k < |D| both keep the k largest P_i and do not renormalise.
    rng = np.random.default_rng(3)
    trajs, scores = _pool(rng, 10, 4, 15)
    prefix = rng.integers(4, size=15).tolist()
    ours = _server_rewards(trajs, scores, prefix, 4, k=3)
    memory = [[onehot(a, 4) for a in t] + [s] for t, s in zip(trajs, scores, strict=True)]
    data = []
    for t, a in enumerate(prefix):
        data.append(onehot(a, 4))
        if t == 0:
            continue  # at t = 0 many P_i tie: their argmax order and SPEC's tie rule differ
        r_exact = authors_predict_modified(memory, t, data, k=3, eps=1e-7, digits=None)
        p = np.array(
            [
                1.0
                / max(1e-300, sum(2 * (x != y) for x, y in zip(tr, prefix[: t + 1], strict=False)))
                for tr in trajs
            ]
        )
        if len(set(np.round(np.sort(p)[-4:], 12))) < 4:
            continue  # a tie at the k-th place: the tie rules differ (documented)
        assert ours[t][1] == pytest.approx(r_exact, abs=1e-6), t
