"""The authors' saved results (``experiments/authors-data/``, see its README): one run per
arm, summarised the way the report's claims are measured."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["AUTHORS_DATA", "authors_summary"]

#: ``experiments/authors-data``.
AUTHORS_DATA = Path(__file__).resolve().parents[1] / "authors-data"


def _load(name: str) -> np.ndarray | None:
    path = AUTHORS_DATA / f"{name}.npy"
    return np.load(path, allow_pickle=False) if path.is_file() else None


def _first_at_least(x: np.ndarray, level: float) -> str:
    hits = np.flatnonzero(x >= level)
    return f"episode {int(hits[0]) + 1}" if hits.size else "never"


def authors_summary(experiment: str) -> str:
    """One cell of the claims table: what the authors' saved runs say (or ``""``)."""
    if experiment == "cartpole":
        parts = []
        for arm, name in (("plain", "natural"), ("TAMRM", "metarewardmodel"), ("PBRS", "PBRS")):
            x = _load(f"cartpole__v2_{name}_AC")
            if x is not None:
                parts.append(
                    f"{arm}: running reward {x[-1]:.0f} at episode {x.size}, >= 195 "
                    f"{_first_at_least(x, 195)}"
                )
        return "; ".join(parts) + " (1 run each; running reward, not the 100-episode mean)"
    if experiment == "mountaincar":
        parts = []
        for arm, names in (
            ("plain", ("dqn_500", "normal_dqn_500")),
            ("TAMRM", ("v2_metarewardmodel_500", "meta_reward_model_500")),
            ("PBRS", ("v2_PBRS_500",)),
        ):
            totals = [x[-1] for n in names if (x := _load(f"mountaincar__{n}")) is not None]
            if totals:
                parts.append(f"{arm} " + " and ".join(f"{int(t):,}" for t in totals))
        return "total steps after the first episode, 500 episodes: " + "; ".join(parts)
    if experiment == "maze":
        parts = []
        for arm, name in (("plain", "normal"), ("TAMRM", "metarewardmodel"), ("PBRS", "pbrs")):
            x = _load(f"maze__V2_{name}")
            if x is not None:
                parts.append(f"{arm} {int(x[-1]):,}")
        return (
            "running steps per episode at episode 200 (their observation bug: the agent "
            "always sees the start): " + ", ".join(parts)
        )
    return ""
