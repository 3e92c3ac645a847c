"""Plots of the report: each group's learning curves (steps per episode, every arm)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from tamrm.trial.stats import rolling_mean, t_interval

from tamrm_experiments.configs import ARMS, EXPERIMENTS
from tamrm_experiments.load import Run

__all__ = ["curves", "plot_experiment"]


def curves(
    runs: list[Run], window: int, log: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-episode mean over seeds of the smoothed steps, with a 95% t band.

    With ``log``, mean and band are computed on log10 of the smoothed steps (a geometric
    mean: steps per episode are heavily skewed) and transformed back.
    """
    n = max(len(r.df) for r in runs)
    mat = np.full((len(runs), n), np.nan)
    for i, r in enumerate(runs):
        sm = rolling_mean(r.df["steps"].to_numpy(dtype=np.float64), window)
        mat[i, : sm.size] = np.log10(sm) if log else sm
    mean = np.nanmean(mat, axis=0)
    low = np.full(n, np.nan)
    high = np.full(n, np.nan)
    for j in range(n):
        iv = t_interval(mat[:, j].tolist())
        low[j], high[j] = iv.low, iv.high
    if log:
        mean, low, high = 10**mean, 10**low, 10**high
    return np.arange(1, n + 1), mean, low, high


def plot_experiment(exp_name: str, runs: list[Run], path: Path, title: str = "") -> None:
    """Learning curve (steps per episode) of every arm: mean over seeds with a 95% band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    exp = EXPERIMENTS[exp_name]
    window = exp.plot_window
    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=110)
    colors = {"plain": "#444444", "pbrs": "#1f77b4", "knn": "#2ca02c", "tamrm": "#d62728"}
    lo_all, hi_all = math.inf, 0.0
    for arm in ARMS:
        arm_runs = [r for r in runs if r.arm == arm and len(r.df)]
        if not arm_runs:
            continue
        x, mean, low, high = curves(arm_runs, window, log=exp.plot_log)
        ax.plot(x, mean, color=colors[arm], label=f"{ARMS[arm].label} (n={len(arm_runs)})", lw=1.4)
        ax.fill_between(x, low, high, color=colors[arm], alpha=0.18, lw=0)
        lo_all = min(lo_all, float(np.nanmin(mean)))
        hi_all = max(hi_all, float(np.nanmax(mean)))
    ax.set_ylabel(exp.plot_ylabel())
    if exp.plot_log:
        ax.set_yscale("log")
        if hi_all > 0:
            # Bands of few seeds can be very wide: keep the means readable.
            ax.set_ylim(max(1.0, lo_all / 4), hi_all * 4)
    exp.decorate(ax)
    switch = runs[0].budget.get("switch_after") if runs else None
    if switch:
        ax.axvline(switch + 0.5, color="k", ls="--", lw=0.8)
    ax.set_xlabel("episode")
    how = "geometric mean" if exp.plot_log else "mean"
    ax.set_title(f"{title or exp.title}\n{how} over seeds, band = 95% t-interval", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
