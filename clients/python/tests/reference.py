"""A naive, independent Python implementation of SPEC §2-§6, used to check the server.

Deliberately simple: distances recomputed from scratch (O(|D|·t)), no incremental state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)
class RefTrajectory:
    actions: np.ndarray  # (L,) int or (L, m) float32
    score: float
    seq: int


@dataclass
class RefConfig:
    num_actions: int = 0
    action_dim: int = 0
    pool_capacity: int = 20
    k: int = 20
    start_step: int = 10
    min_pool_size: int = 20
    alpha: float = 0.8
    beta: float = 0.8
    gamma: float = 0.99
    max_trajectory_len: int = 100000
    gate_potential: bool = False
    require_score_spread: bool = False

    @classmethod
    def of(cls, config: object) -> RefConfig:
        return cls(**{name: getattr(config, name) for name in cls.__dataclass_fields__})


def encode(action: object, cfg: RefConfig) -> np.ndarray:
    if cfg.num_actions:
        out = np.zeros(cfg.num_actions)
        out[int(action)] = 1.0  # type: ignore[call-overload]
        return out
    return np.asarray(action, dtype=np.float32).astype(np.float64)


def delta(a: object, b: object, cfg: RefConfig) -> float:
    d = encode(a, cfg) - encode(b, cfg)
    return float(np.dot(d, d))


def dis(traj: RefTrajectory, episode: list[object], t: int, cfg: RefConfig) -> float:
    return sum(delta(traj.actions[j], episode[j], cfg) for j in range(t + 1))


def knn_reward(
    pool: list[RefTrajectory], episode: list[object], t: int, cfg: RefConfig
) -> tuple[bool, float]:
    """(active, r(t)) for the episode's actions a'_0..a'_t (episode has >= t+1 entries)."""
    if len(pool) < cfg.min_pool_size or not pool:
        return False, 0.0
    l_min = min(len(p.actions) for p in pool)
    if not (t >= cfg.start_step and t < l_min and t < cfg.max_trajectory_len):
        return False, 0.0
    scores = [p.score for p in pool]
    s_min, s_max = min(scores), max(scores)
    if cfg.require_score_spread and not s_max > s_min:
        return False, 0.0  # SPEC v1.3 §3: a pool of equal scores tells nothing
    d = [dis(p, episode, t, cfg) for p in pool]
    zeros = [i for i, x in enumerate(d) if x == 0.0]
    if zeros:
        prob = [1.0 / len(zeros) if i in zeros else 0.0 for i in range(len(pool))]
    else:
        inv = [1.0 / x for x in d]
        total = sum(inv)
        prob = [x / total for x in inv]
    if s_max == s_min:
        x = [1.0] * len(pool)
    else:
        x = [(s - s_min) / (s_max - s_min) for s in scores]
    order = sorted(range(len(pool)), key=lambda i: (-prob[i], -x[i], pool[i].seq))
    top = order[: min(cfg.k, len(pool))]
    f = sum(x[i] * prob[i] for i in top)
    return True, math.exp(f) - math.exp(0.5)


def potential(
    cfg: RefConfig, value: float | None, next_value: float | None, terminated: bool
) -> float:
    if value is None or next_value is None:
        return 0.0
    v = float(np.float32(value))
    v_next = 0.0 if terminated else float(np.float32(next_value))
    return cfg.gamma * v_next - v


@dataclass
class RefPool:
    """The pool and its update rule (SPEC §6)."""

    cfg: RefConfig
    trajectories: list[RefTrajectory] = field(default_factory=list)
    next_seq: int = 0
    version: int = 0

    def offer(self, actions: np.ndarray, score: float) -> bool:
        actions = np.asarray(actions)[: self.cfg.max_trajectory_len]
        if len(self.trajectories) < self.cfg.pool_capacity:
            self.trajectories.append(RefTrajectory(actions, score, self.next_seq))
        else:
            worst = min(self.trajectories, key=lambda p: (p.score, p.seq))
            if not score > worst.score:
                return False
            self.trajectories.remove(worst)
            self.trajectories.append(RefTrajectory(actions, score, self.next_seq))
        self.next_seq += 1
        self.version += 1
        return True

    def sync(self, pool: object) -> None:
        """Take the server's pool (a ``tamrm.Pool``) as the reference state."""
        self.trajectories = [
            RefTrajectory(np.asarray(t.actions), t.score, t.seq)
            for t in pool.trajectories  # type: ignore[attr-defined]
        ]
        self.version = pool.pool_version  # type: ignore[attr-defined]
        self.next_seq = max((t.seq for t in self.trajectories), default=-1) + 1


class RefStream:
    """Per-env episode state of one stream, shaping entries against a shared RefPool."""

    def __init__(self, pool: RefPool, num_envs: int) -> None:
        self.pool = pool
        self.episodes: list[list[object]] = [[] for _ in range(num_envs)]
        self.returns = [0.0] * num_envs

    def abandon(self, env: int) -> None:
        """SPEC §12: drop the env's current episode without offering it to the pool."""
        self.episodes[env] = []
        self.returns[env] = 0.0

    def shape(
        self,
        env: int,
        action: object,
        reward: float,
        terminated: bool = False,
        truncated: bool = False,
        value: float | None = None,
        next_value: float | None = None,
        score: float | None = None,
    ) -> dict[str, float]:
        cfg = self.pool.cfg
        ep = self.episodes[env]
        ep.append(action)
        t = len(ep) - 1
        active, r = knn_reward(self.pool.trajectories, ep, t, cfg)
        f = potential(cfg, value, next_value, terminated)
        if cfg.gate_potential and not active:
            f = 0.0  # SPEC v1.1 §4: with gating, F counts only where the kNN term is active
        self.returns[env] += reward
        out = {
            "reward": reward + cfg.alpha * r + cfg.beta * f,
            "knn_reward": r,
            "potential": f,
            "step": t,
            "knn_active": active,
        }
        if terminated or truncated:
            final_score = self.returns[env] if score is None else score
            self.pool.offer(np.asarray(ep), final_score)
            self.episodes[env] = []
            self.returns[env] = 0.0
        return out


def assert_pools_identical(got: object, want: object) -> None:
    """Two ``tamrm.Pool`` answers hold the same trajectories, bit for bit (seq, score, actions)."""
    assert got.task_id == want.task_id  # type: ignore[attr-defined]
    assert got.pool_version == want.pool_version  # type: ignore[attr-defined]
    a, b = got.trajectories, want.trajectories  # type: ignore[attr-defined]
    assert [(t.seq, t.score) for t in a] == [(t.seq, t.score) for t in b]
    for x, y in zip(a, b, strict=True):
        assert x.actions.dtype == y.actions.dtype and x.actions.shape == y.actions.shape
        assert np.array_equal(x.actions, y.actions), (x.seq, x.actions, y.actions)


def assert_tasks_identical(got: object, want: object) -> None:
    """Two ``tamrm.Task`` answers agree: id, resolved config, stats (but ``open_streams``)."""
    assert got.task_id == want.task_id  # type: ignore[attr-defined]
    assert got.config == want.config  # type: ignore[attr-defined]
    skip = {"open_streams"}
    stats_a = {k: v for k, v in vars(got.stats).items() if k not in skip}  # type: ignore[attr-defined]
    stats_b = {k: v for k, v in vars(want.stats).items() if k not in skip}  # type: ignore[attr-defined]
    assert stats_a == stats_b
