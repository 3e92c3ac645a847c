"""What a trial runs: its settings, its arms, and the key of each run.

A trial is a set of runs, one per (arm, seed). Every run of one seed gets the same
environment seed and the same model seed (paired seeds); arms differ only in how the
rewards the learner sees are shaped:

========  =====================================================  ==================
arm       shaping                                                alpha, beta
========  =====================================================  ==================
plain     none: the learner on the environment, no tamrm at all  -
null      through the same shaping path as the others            0, 0
knn       the kNN term only                                      alpha, 0
pbrs      the potential term only (the model's own values)       0, beta
tamrm     both terms                                             alpha, beta
========  =====================================================  ==================

``null`` learns bit for bit what ``plain`` learns: the harness itself adds nothing.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

__all__ = [
    "ALGOS",
    "ARMS",
    "DEFAULT_ARMS",
    "SHAPING_ARMS",
    "Margin",
    "TrialSettings",
    "arm_task_config",
    "run_name",
]

#: The Stable-Baselines3 algorithms a trial can train, by the name on the command line.
ALGOS = ("a2c", "ppo", "dqn")
#: Every arm, in report order.
ARMS = ("plain", "null", "knn", "pbrs", "tamrm")
#: The arms run when none are named.
DEFAULT_ARMS = ("plain", "tamrm")
#: The arms that go through tamrm (every arm but ``plain``).
SHAPING_ARMS = frozenset(ARMS) - {"plain"}
#: The terms each shaping arm turns off (``alpha`` and ``beta`` forced to 0).
_ZEROED = {"null": ("alpha", "beta"), "knn": ("beta",), "pbrs": ("alpha",), "tamrm": ()}


@dataclass(frozen=True)
class Margin:
    """The equivalence margin: a fraction of plain's mean AUC, or an absolute return."""

    value: float
    relative: bool

    @classmethod
    def parse(cls, text: str) -> Margin:
        """``"10%"`` (relative to plain's mean AUC) or ``"5.0"`` (in units of return).

        Raises:
            ValueError: Not a positive finite number, with or without ``%``.
        """
        body = text.strip()
        relative = body.endswith("%")
        try:
            value = float(body[:-1] if relative else body)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise ValueError(
                f"--margin {text!r}: a positive number, relative to plain's AUC with '%' "
                "(10%) or in units of return without (5.0)"
            )
        return cls(value / 100 if relative else value, relative)

    def of(self, plain_auc: float) -> float:
        """The margin in units of return, given plain's mean AUC."""
        return self.value * abs(plain_auc) if self.relative else self.value

    def __str__(self) -> str:
        return f"{self.value * 100:g} % of plain's AUC" if self.relative else f"{self.value:g}"


@dataclass(frozen=True)
class TrialSettings:
    """Everything a trial runs and reports, as recorded in ``DIR/trial.json``.

    Attributes:
        env: A registered gymnasium id.
        algo: ``a2c``, ``ppo`` or ``dqn`` (Stable-Baselines3).
        timesteps: Environment steps per run (summed over the vector env).
        seeds: Paired seeds per arm: ``seed0 .. seed0 + seeds - 1``.
        arms: The arms, ``plain`` first when present.
        env_modules: Modules imported before the env is made (they register it).
        env_kwargs: Keyword arguments of ``gymnasium.make``.
        seed0: The first seed.
        task: The ``TaskConfig`` fields set on the command line (the others: SPEC's
            defaults); ``alpha`` and ``beta`` are then zeroed per arm.
        hyperparams: The algorithm's settings in rl-zoo3's layout (one env's section),
            without ``n_timesteps``; empty for Stable-Baselines3's defaults.
        hyperparams_file: Where they were read, for the report.
        threshold: The return whose first crossing is timed, if any.
        margin: The equivalence margin of "no difference large enough to matter".
        verdict: Whether a verdict is asked for (it needs two seeds or more).
        server: Shape through this server with local sessions instead of an embedded
            engine (the values are the same).
        name: The trial's name: the prefix of its task ids on a server.
    """

    env: str
    algo: str
    timesteps: int
    seeds: int
    arms: tuple[str, ...] = DEFAULT_ARMS
    env_modules: tuple[str, ...] = ()
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    seed0: int = 0
    task: Mapping[str, Any] = field(default_factory=dict)
    hyperparams: Mapping[str, Any] = field(default_factory=dict)
    hyperparams_file: str | None = None
    threshold: float | None = None
    margin: Margin = field(default_factory=lambda: Margin(0.1, True))
    verdict: bool = True
    server: str | None = None
    name: str = "trial"

    @property
    def seed_list(self) -> list[int]:
        """The paired seeds, in order."""
        return list(range(self.seed0, self.seed0 + self.seeds))

    def runs(self) -> list[tuple[str, int]]:
        """Every (arm, seed) of the trial, seed by seed, so that pairs finish together."""
        return [(arm, seed) for seed in self.seed_list for arm in self.arms]

    def run_config(self, arm: str) -> dict[str, Any]:
        """What one arm's runs depend on (besides the seed): equal configs, equal runs.

        The backend (engine or server) is not part of it: both give the same values.
        """
        return {
            "env": self.env,
            "env_modules": list(self.env_modules),
            "env_kwargs": dict(self.env_kwargs),
            "algo": self.algo,
            "timesteps": self.timesteps,
            "hyperparams": dict(self.hyperparams),
            "arm": arm,
            "task": arm_task_config(arm, self.task),
        }

    def to_json(self) -> dict[str, Any]:
        """A JSON-able form (``from_json`` reads it back)."""
        out = asdict(self)
        out["arms"] = list(self.arms)
        out["env_modules"] = list(self.env_modules)
        out["margin"] = {"value": self.margin.value, "relative": self.margin.relative}
        return json.loads(json.dumps(out))  # type: ignore[no-any-return]

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> TrialSettings:
        """The settings written by :meth:`to_json`."""
        kwargs = dict(data)
        kwargs["arms"] = tuple(kwargs["arms"])
        kwargs["env_modules"] = tuple(kwargs.get("env_modules", ()))
        kwargs["margin"] = Margin(**kwargs["margin"])
        return cls(**kwargs)

    def with_(self, **changes: Any) -> TrialSettings:
        """A copy with some settings changed."""
        return replace(self, **changes)


def arm_task_config(arm: str, task: Mapping[str, Any]) -> dict[str, Any] | None:
    """The ``create_task`` keywords of an arm's task (``None`` for ``plain``: no task).

    Raises:
        ValueError: Not an arm.
    """
    if arm == "plain":
        return None
    if arm not in _ZEROED:
        raise ValueError(f"unknown arm {arm!r}; the arms are {', '.join(ARMS)}")
    config = dict(task)
    for term in _ZEROED[arm]:
        config[term] = 0.0
    return config


_TASK_ID_CHARS = re.compile(r"[^A-Za-z0-9._:/-]+")


def run_name(arm: str, seed: int) -> str:
    """The run's file stem under ``DIR/runs/``: ``<arm>-<seed>``."""
    return f"{arm}-{seed}"


def task_id(settings: TrialSettings, arm: str, seed: int) -> str:
    """The task of a run on a server: ``trial-<name>/<arm>/s<seed>`` (SPEC's id characters)."""
    name = _TASK_ID_CHARS.sub("-", settings.name).strip("-") or "trial"
    return f"trial-{name}/{arm}/s{seed}"[:128]
