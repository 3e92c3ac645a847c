"""Turn the raw per-episode CSVs into ``docs/reproduction.md`` and its plots.

Everything in the page is computed from the runs directory: the tables, the verdicts
and the closing note. Nothing is typed in by hand except the paper's own figures and
the list of deviations from the paper (which describe the setup, not the results).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tamrm_experiments.args import parser
from tamrm_experiments.configs import ARMS, EXPERIMENTS, make_specs
from tamrm_experiments.envs import MAZE_NEW_START, MAZE_START, maze_shortest_path
from tamrm_experiments.experiments.base import Metric
from tamrm_experiments.stats import (
    Interval,
    rolling_mean,
    t_interval,
    welch_interval,
)

__all__ = ["Run", "load_runs", "run_metrics", "write_report"]


@dataclass
class Run:
    """One finished run: its sidecar and its per-episode rows."""

    experiment: str
    arm: str
    seed: int
    meta: dict[str, Any]
    df: pd.DataFrame

    @property
    def budget(self) -> dict[str, Any]:
        """The run's budget (episodes, caps)."""
        return dict(self.meta["spec"]["budget"])


def load_runs(runs_dir: Path) -> list[Run]:
    """Load every complete run under ``runs_dir``."""
    runs = []
    for meta_path in sorted(runs_dir.glob("*/*/seed*.json")):
        meta = json.loads(meta_path.read_text())
        csv_path = meta_path.with_suffix(".csv")
        if not meta.get("complete") or not csv_path.is_file():
            continue
        spec = meta["spec"]
        runs.append(Run(spec["experiment"], spec["arm"], spec["seed"], meta, pd.read_csv(csv_path)))
    return runs


# -- metrics ---------------------------------------------------------------------------


#: Kept for callers of the old names: each experiment's module is the one source.
METRICS: dict[str, tuple[Metric, ...]] = {n: e.metrics for n, e in EXPERIMENTS.items()}
HEADLINE: dict[str, str] = {n: e.headline for n, e in EXPERIMENTS.items()}


def run_metrics(run: Run) -> dict[str, float]:
    """The metrics of one run (``nan`` where undefined)."""
    df = run.df
    steps = df["steps"].to_numpy(dtype=np.float64)
    out: dict[str, float] = {
        "episodes": float(len(df)),
        "total_steps": float(steps.sum()),
        "last20": float(steps[-20:].mean()) if len(steps) else math.nan,
        "successes": float(df["success"].sum()) if len(df) else 0.0,
    }
    # A run stopped by its step cap has an unfinished last episode: its steps count in the
    # totals (which are then lower bounds), in the phase it belongs to.
    unfinished = max(0.0, float(run.meta.get("total_steps", 0)) - out["total_steps"])
    out["total_steps"] += unfinished
    out.update(EXPERIMENTS[run.experiment].extra_metrics(df, run.meta, unfinished))
    return out


# -- formatting ------------------------------------------------------------------------


def _fmt(value: float, fmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return fmt.format(value)


def _fmt_interval(iv: Interval, fmt: str) -> str:
    if iv.n == 0:
        return "-"
    if iv.n == 1 or math.isnan(iv.low):
        return f"{_fmt(iv.mean, fmt)} (n=1)"
    return f"{_fmt(iv.mean, fmt)} [{_fmt(iv.low, fmt)}, {_fmt(iv.high, fmt)}]"


@dataclass
class Comparison:
    """Arm minus plain on one metric."""

    arm: str
    metric: Metric
    diff: Interval
    better: bool | None = None  # True better, False worse, None no detectable difference
    text: str = field(default="")


def compare(
    metric: Metric, arm_values: list[float], plain_values: list[float], arm: str
) -> Comparison:
    """Welch interval of (arm - plain) and a verdict in words."""
    diff = welch_interval(arm_values, plain_values)
    if diff.n < 2 or not diff.excludes(0.0):
        better = None
    else:
        better = (diff.high < 0) if metric.lower_is_better else (diff.low > 0)
    rel = ""
    base = float(np.nanmean(plain_values)) if len(plain_values) else math.nan
    if base and not math.isnan(base) and not math.isnan(diff.mean):
        rel = f" ({diff.mean / base:+.0%} of plain)"
    ci = (
        f"[{_fmt(diff.low, metric.fmt)}, {_fmt(diff.high, metric.fmt)}]"
        if not math.isnan(diff.low)
        else "[n/a]"
    )
    word = {True: "better", False: "worse", None: "no detectable difference"}[better]
    text = f"{_fmt(diff.mean, metric.fmt)}{rel}, 95% CI {ci}: {word}"
    return Comparison(arm, metric, diff, better, text)


# -- plots -----------------------------------------------------------------------------


def _curves(
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
        iv = t_interval(mat[:, j])
        low[j], high[j] = iv.low, iv.high
    if log:
        mean, low, high = 10**mean, 10**low, 10**high
    return np.arange(1, n + 1), mean, low, high


def plot_experiment(exp_name: str, runs: list[Run], path: Path) -> None:
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
        x, mean, low, high = _curves(arm_runs, window, log=exp.plot_log)
        ax.plot(x, mean, color=colors[arm], label=f"{ARMS[arm].label} (n={len(arm_runs)})", lw=1.4)
        ax.fill_between(x, low, high, color=colors[arm], alpha=0.18, lw=0)
        lo_all = min(lo_all, float(np.nanmin(mean)))
        hi_all = max(hi_all, float(np.nanmax(mean)))
    exp.decorate(ax)
    ax.set_ylabel(exp.plot_ylabel())
    if exp.plot_log:
        ax.set_yscale("log")
        if hi_all > 0:
            # Bands of few seeds can be very wide: keep the means readable.
            ax.set_ylim(max(1.0, lo_all / 4), hi_all * 4)
    switch = runs[0].budget.get("switch_after") if runs else None
    if switch:
        ax.axvline(switch + 0.5, color="k", ls="--", lw=0.8)
    ax.set_xlabel("episode")
    how = "geometric mean" if exp.plot_log else "mean"
    ax.set_title(f"{exp.title}\n{how} over seeds, band = 95% t-interval", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# -- the page --------------------------------------------------------------------------


def _invocations(runs_dir: Path) -> list[dict[str, Any]]:
    path = runs_dir / "invocations.jsonl"
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def _requested(runs_dir: Path) -> list[tuple[str, str, int]]:
    """(experiment, arm, seed) of every run that some grid invocation asked for, in grid
    order: each invocation's recorded command line parsed as the ``run`` command does."""
    import shlex

    keys: dict[tuple[str, str, int], None] = {}
    for inv in _invocations(runs_dir):
        argv = shlex.split(inv.get("command", ""))
        if "tamrm_experiments" not in argv:
            continue
        try:
            args = parser().parse_args(argv[argv.index("tamrm_experiments") + 1 :])
        except SystemExit:  # a command line this version cannot parse
            continue
        if args.command != "run":
            continue
        profile = args.profile or ("quick" if args.quick else "full")
        for spec in make_specs(profile, args.seeds, args.experiments, args.arms, args.first_seed):
            keys[(spec.experiment, spec.arm, spec.seed)] = None
    return list(keys)


def _busy_minutes(invocations: list[dict[str, Any]]) -> float:
    """Minutes in the union of the invocations' [start, finish] intervals: wall time
    during which the grid was running, not counting the gaps between sessions."""
    import datetime as dt

    spans = []
    for inv in invocations:
        if "started_utc" in inv and "finished_utc" in inv:
            t0 = dt.datetime.strptime(inv["started_utc"], "%Y-%m-%dT%H:%M:%SZ").timestamp()
            t1 = dt.datetime.strptime(inv["finished_utc"], "%Y-%m-%dT%H:%M:%SZ").timestamp()
            spans.append((t0, max(t0, t1)))
    busy = 0.0
    end = float("-inf")
    for t0, t1 in sorted(spans):
        if t1 > end:
            busy += t1 - max(t0, end)
            end = t1
    return busy / 60


def _budget_line(exp_name: str, runs: list[Run]) -> str:
    exp = EXPERIMENTS[exp_name]
    budgets = {json.dumps(r.budget, sort_keys=True) for r in runs}
    parts = []
    for b in sorted(budgets):
        bd = json.loads(b)
        reduced = []
        if bd["episodes"] < exp.episodes:
            reduced.append(f"episodes {bd['episodes']} < paper's {exp.episodes}")
        if bd["max_episode_steps"] < exp.max_episode_steps:
            reduced.append(
                f"episode cap {bd['max_episode_steps']:,} < {exp.max_episode_steps:,} steps"
            )
        note = ("; **reduced**: " + ", ".join(reduced)) if reduced else " (the paper's budget)"
        parts.append(
            f"{bd['episodes']} episodes, at most {bd['max_episode_steps']:,} steps per episode, "
            f"at most {bd['max_total_steps']:,} steps per run{note}"
        )
    return "; ".join(parts)


#: Totals that a run stopped by its step cap only bounds from below.
CENSORABLE = ("total_steps", "phase1_steps", "phase2_steps")


def _censoring_caveat(comp: Comparison, arm_censored: bool, plain_censored: bool) -> Comparison:
    """Keep a verdict only if censoring (totals that are lower bounds) cannot reverse it."""
    # A censored total understates the true one. If only plain is censored, "arm better"
    # stands (plain's true total is even larger); if only the arm is, "arm worse" stands.
    safe = (plain_censored and not arm_censored and comp.better is True) or (
        arm_censored and not plain_censored and comp.better is False
    )
    if safe:
        comp.text += " (some totals are lower bounds; they can only widen this gap)"
    elif comp.better is None:
        comp.text += " (some totals are lower bounds)"
    else:
        comp.better = None
        comp.text += (
            " - but some totals are lower bounds (runs stopped by the step cap), so this "
            "is counted as undecided"
        )
    return comp


def _experiment_section(
    exp_name: str, runs: list[Run], plots_rel: str, plots_dir: Path
) -> tuple[list[str], dict[str, Any]]:
    exp = EXPERIMENTS[exp_name]
    lines = [f"## {exp.title}", ""]
    if not runs:
        return [*lines, "No finished runs.", ""], {}
    metrics = {arm: [] for arm in ARMS}  # type: dict[str, list[dict[str, float]]]
    censored = {arm: 0 for arm in ARMS}
    for r in runs:
        metrics[r.arm].append(run_metrics(r))
        censored[r.arm] += int(bool(r.meta.get("censored")))
    lines.append(f"Budget: {_budget_line(exp_name, runs)}.")
    if len({json.dumps(r.budget, sort_keys=True) for r in runs}) > 1:
        lines += [
            "",
            "> **Mixed budgets**: this experiment's runs do not share one budget, and the "
            "statistics below pool them. Rerun its runs under one profile before reading "
            "the numbers.",
        ]
    lines.append("")
    mlist = exp.metrics
    head = ["arm", "seeds", "paper", exp.status_column()]
    head += [m.label for m in mlist]
    any_censored = any(censored.values())
    if any_censored:
        head.append("episodes done")
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for arm in ARMS:
        ms = metrics[arm]
        if not ms:
            continue
        row = [ARMS[arm].label, str(len(ms)), exp.paper[arm], exp.status_cell(ms, censored[arm])]
        for m in mlist:
            iv = t_interval([x[m.key] for x in ms])
            cell = _fmt_interval(iv, m.fmt)
            if censored[arm] and m.key in CENSORABLE:
                cell = "≥ " + cell
            row.append(cell)
        if any_censored:
            row.append(_fmt_interval(t_interval([x["episodes"] for x in ms]), "{:,.1f}"))
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append(
        "Cells: mean over seeds [95% Student-t confidence interval over seeds]. "
        + (
            "A run stopped by its total-step cap has fewer episodes; its totals are lower "
            "bounds (marked ≥)."
            if any(censored.values())
            else ""
        )
    )
    lines.append("")
    head_metric = next(m for m in mlist if m.key == exp.headline)
    plain = [m[head_metric.key] for m in metrics["plain"]]
    comps: dict[str, Comparison] = {}
    if plain:
        lines.append(f"Difference to plain on *{head_metric.label}* (Welch 95% CI):")
        lines.append("")
        for arm in ARMS:
            if arm == "plain" or not metrics[arm]:
                continue
            comp = compare(head_metric, [m[head_metric.key] for m in metrics[arm]], plain, arm)
            if head_metric.key in CENSORABLE and (censored[arm] or censored["plain"]):
                comp = _censoring_caveat(comp, bool(censored[arm]), bool(censored["plain"]))
            comps[arm] = comp
            lines.append(f"- {ARMS[arm].label}: {comp.text}")
        lines.append("")
    lines += _diagnostics(runs)
    png = plots_dir / f"{exp_name}.png"
    plot_experiment(exp_name, runs, png)
    lines.append(f"![{exp.title}]({plots_rel}/{exp_name}.png)")
    lines.append("")
    return lines, {"metrics": metrics, "comparisons": comps, "censored": censored}


def _agreement(exp_name: str, result: dict[str, Any]) -> str:
    """One sentence per experiment: does our measurement agree with the paper's claim?"""
    if not result:
        return f"- **{EXPERIMENTS[exp_name].title}**: no data."
    comps: dict[str, Comparison] = result["comparisons"]
    metrics = result["metrics"]

    def verdict(arm: str) -> str:
        c = comps.get(arm)
        if c is None:
            return "not measured"
        return {
            True: "better than plain",
            False: "worse than plain",
            None: "not distinguishable from plain",
        }[c.better]

    return EXPERIMENTS[exp_name].agreement(comps, metrics, verdict)


def _claims(results: dict[str, dict[str, Any]]) -> list[tuple[str, str]]:
    """The paper's claims, each with our verdict: reproduced, contradicted or undecided."""
    out: list[tuple[str, str]] = []

    def cat(better: bool | None, want: bool) -> str:
        if better is None:
            return "undecided"
        return "reproduced" if better == want else "contradicted"

    for exp_name, res in results.items():
        if not res:
            continue
        exp = EXPERIMENTS[exp_name]
        comps: dict[str, Comparison] = res["comparisons"]
        tam, pbrs = comps.get("tamrm"), comps.get("pbrs")
        out += exp.extra_claims(res["metrics"])
        if tam is not None:
            out.append((f"{exp.short}: {exp.claim_check}", cat(tam.better, True)))
        if pbrs is not None and exp.pbrs_claim:
            out.append(
                (
                    f"{exp.short}: PBRS alone does not help (is worse than plain)",
                    cat(pbrs.better, False),
                )
            )
    return out


def _closing(results: dict[str, dict[str, Any]], n_seeds: int) -> list[str]:
    claims = _claims(results)
    lines = ["## Closing note: agreement with the paper", ""]
    for label, key in (
        ("Agrees with the paper", "reproduced"),
        ("Disagrees with the paper", "contradicted"),
        ("Not decided by our data (no difference detectable at 95%)", "undecided"),
    ):
        items = [c for c, v in claims if v == key]
        lines.append(f"**{label}**" + (":" if items else ": none."))
        lines += [f"- {c}" for c in items]
        lines.append("")
    # The ablation: which term carries the effect?
    abl = []
    for exp_name, res in results.items():
        if not res:
            continue
        comps = res["comparisons"]
        words = {
            arm: {True: "better", False: "worse", None: "no different"}[comps[arm].better]
            for arm in ("knn", "pbrs", "tamrm")
            if arm in comps
        }
        if words:
            title = EXPERIMENTS[exp_name].title.split(" (")[0]
            abl.append(
                f"- {title}: kNN only {words.get('knn', '?')}, PBRS only "
                f"{words.get('pbrs', '?')}, both {words.get('tamrm', '?')} than plain."
            )
    lines += ["**Ablation (which term does the work)**:", *abl, ""]
    lines += [
        "Caveats: budgets are reduced where stated above; the learners are SB3's, not the "
        f"authors'; {n_seeds} seeds or fewer per arm (see the tables) give wide intervals, "
        "so 'not decided' means "
        "the effect, if any, "
        "is smaller than what these seeds can resolve, not that there is none.",
        "",
    ]
    return lines


def _answer(results: dict[str, dict[str, Any]], runs: list[Run]) -> list[str]:
    """The headline: per arm, in how many experiments it beat plain, lost, or tied."""
    lines = []
    reduced = []
    for exp_name, exp in EXPERIMENTS.items():
        budgets = {json.dumps(r.budget, sort_keys=True) for r in runs if r.experiment == exp_name}
        for b in budgets:
            bd = json.loads(b)
            if bd["episodes"] < exp.episodes:
                reduced.append(f"{exp.title}: {bd['episodes']} episodes instead of {exp.episodes}")
    if reduced:
        lines += [
            "> **Reduced budgets** (to fit the compute of one session; see each experiment): "
            + "; ".join(reduced)
            + ".",
            "",
        ]
    for arm in ("tamrm", "knn", "pbrs"):
        counts = {True: [], False: [], None: []}  # type: dict[bool | None, list[str]]
        for exp_name, res in results.items():
            comp = res.get("comparisons", {}).get(arm) if res else None
            if comp is not None:
                counts[comp.better].append(EXPERIMENTS[exp_name].title.split(" (")[0])
        n = sum(len(v) for v in counts.values())
        if not n:
            continue
        parts = []
        for key, word in ((True, "better"), (False, "worse"), (None, "not distinguishable")):
            if counts[key]:
                parts.append(f"{word} in {len(counts[key])} ({', '.join(counts[key])})")
        lines.append(
            f"- **{ARMS[arm].label}** vs plain, on each experiment's headline metric "
            f"(Welch 95% CI over seeds): " + "; ".join(parts) + f" of {n} experiments."
        )
    lines.append("")
    return lines


def _diagnostics(runs: list[Run]) -> list[str]:
    """Per arm: how much each shaping term contributed, per step."""
    lines = [
        "Shaping diagnostics (mean over seeds of per-run totals / steps): the kNN reward "
        "r(t) and the potential term F as computed by the server, before the weights "
        "alpha and beta, and the share of steps where the kNN term was active.",
        "",
        "| arm | r(t) per step | F per step | kNN active | shaped minus env reward per step |",
        "|---|---|---|---|---|",
    ]
    for arm in ARMS:
        rs = [r for r in runs if r.arm == arm and len(r.df)]
        if not rs:
            continue

        def per_step(col: str, rs: list[Run] = rs) -> float:
            return float(np.mean([r.df[col].sum() / r.df["steps"].sum() for r in rs]))

        shaped = float(
            np.mean(
                [
                    (r.df["shaped_return"].sum() - r.df["env_return"].sum()) / r.df["steps"].sum()
                    for r in rs
                ]
            )
        )
        lines.append(
            f"| {ARMS[arm].label} | {per_step('knn_sum'):+.3f} | {per_step('potential_sum'):+.3f}"
            f" | {per_step('knn_active_steps'):.0%} | {shaped:+.3f} |"
        )
    lines.append("")
    return lines


#: How to read the numbers: the mechanisms behind them (true whatever the seeds give),
#: pointing to the diagnostics tables rather than quoting numbers that a rerun changes.
READING = [
    "**The potential term mostly rescales the reward.** Phi is the learner's own current "
    "estimate (A2C: V(s); DQN: max_a Q(s, a)), with the learner's gamma. Then "
    "F = gamma V(s') - V(s) is exactly delta - R, where delta = R + gamma V(s') - V(s) is "
    "the TD error of the current estimate, so R + beta F = (1 - beta) R + beta delta: "
    "with beta = 0.8 the learner sees a fifth of the environment reward plus its own TD "
    "error (cart pole: *F per step* is close to -1 against R = +1 in the diagnostics). "
    "Phi also moves as the network learns, so Ng et al.'s guarantee that potential-based "
    "shaping keeps the optimal policy (a fixed Phi) does not apply.",
    "**The kNN term rewards agreeing with stored action sequences at the same time "
    "index.** r(t) lies in [1 - e^0.5, e - e^0.5] = [-0.65, +1.07], of the size of the "
    "environment reward in cart pole and mountain car and far larger than the maze's "
    "(0 except at the goal). It is not potential-based, so it can change which policy "
    "is optimal. In the maze one detour shifts every later index, so a later prefix "
    "rarely matches a stored path, and the term is only active from step N to L_min - 1 "
    "with a full pool: as shorter successes enter the pool L_min shrinks, and the term "
    "is active on few steps (*kNN active* in the diagnostics).",
    "**Many comparisons.** Each experiment compares three arms with plain at 95%: twelve "
    "comparisons in all, so about one 'better' or 'worse' in twelve is expected by chance "
    "alone even if no arm made any difference. A single significant result is weak "
    "evidence; a pattern across seeds, experiments and the curves is stronger.",
    "**Our baselines are not the paper's.** The plain arms are SB3's A2C and DQN, tuned "
    "by their authors for general use; a stronger baseline leaves less room for shaping "
    "to help than the paper's plain learners had (e.g. the paper's plain A2C never "
    "solved cart pole in 1000 episodes).",
]

DEVIATIONS = [
    "The learners are Stable-Baselines3's A2C and DQN, not the authors' code; the shaped "
    "reward R_meta comes from the tamrm server through `tamrm.sb3.ShapedVecEnv` (one gRPC "
    "round trip per environment step), and the potential term uses the SB3 model's own "
    "estimates (A2C: critic V(s); DQN: max_a Q(s, a) of the online network).",
    "Where the paper is silent we use SB3 defaults (A2C: lr 7e-4, n_steps 5, gamma 0.99, "
    "RMSprop, no entropy bonus). DQN: batch 32, learning starts after 200 steps, a gradient "
    "step every 4 steps, target network copied every 200 steps (SB3's default of 10 000 is "
    "longer than most runs).",
    'The paper\'s DQN "decay rate 0.9" is read as the discount gamma = 0.9 (the epsilon is '
    "fixed at 0.1 as the paper's \"epsilon 0.1\"). The server's gamma for the potential term "
    "equals the learner's gamma in every experiment.",
    'The kNN start threshold N (paper: "N > 0", no value) is the service default, 10; '
    "min_pool_size is the pool capacity (the service default): the kNN term starts once the "
    "pool is full, i.e. from episode "
    + ", ".join(
        f"{e.tamrm['pool_capacity'] + 1} ({e.title.split(' (')[0].lower()})"
        for e in EXPERIMENTS.values()
        if e.switch_after is None
    )
    + ", and again 11 episodes after the switch in the modified maze (fresh pool). Before "
    "that, kNN only equals plain and TAMRM equals PBRS only, step for step (same seeds).",
    "Cart pole: `CartPole-v0` of gymnasium (200-step episodes, pole limit 12 degrees; the "
    "paper's text says 15). The training reward is +1 per step and -1 on the step that "
    "fails; the truncation at 200 steps is not a failure. The metric is steps kept up.",
    "Mountain car: `MountainCar-v0` dynamics without Gym's 200-step limit; each episode is "
    "capped at a step limit (a truncation), stated with the budget below. Episode score: "
    "the return (-steps).",
    f"Maze: observation is the raw (x, y) cell as two floats; episode score 100/steps on "
    f"success and 0 on a truncated failure. The start is {MAZE_START} (shortest path "
    f"{maze_shortest_path(MAZE_START)} moves).",
    "Modified maze: after the switch episode (paper: 100; ours: see its budget) the start "
    f"moves to {MAZE_NEW_START} (our choice; shortest path "
    f"{maze_shortest_path(MAZE_NEW_START)} moves). Every arm, plain included, "
    "then continues on a new task id (a fresh, empty pool), as the paper prescribes; the "
    "DQN keeps its network and replay buffer.",
    "The plain arm also goes through the server (alpha = beta = 0), so that every arm runs "
    "the same loop; PBRS only is alpha = 0, kNN only is beta = 0 (the ablation the paper "
    "lacks).",
    "Each run has a safety cap on its total steps; a run that reaches it stops early and "
    "its totals are reported as lower bounds.",
]


def write_report(runs_dir: Path, out: Path, plots_dir: Path) -> None:
    """Write the markdown page ``out`` and the plots into ``plots_dir``."""
    runs = load_runs(runs_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        plots_rel = str(plots_dir.resolve().relative_to(out.parent.resolve()))
    except ValueError:
        plots_rel = str(plots_dir.resolve())
    profiles = sorted({r.meta["spec"]["profile"] for r in runs})
    seeds = sorted({r.seed for r in runs})
    lines = [
        "# Reproduction of the TAMRM paper's experiments",
        "",
        "*Generated by `python -m tamrm_experiments report` from the raw runs in "
        f"`{runs_dir}`; do not edit by hand.*",
        "",
        "Question: does TAMRM shaping, served by tamrm, speed up learning? We rerun the "
        "paper's three experiments (§V) with the real server and the Python client in the "
        "loop, four arms each (plain, PBRS only, kNN only, TAMRM), several seeds, and "
        "report means with 95% confidence intervals over seeds.",
        "",
    ]
    if not runs:
        lines += ["No finished runs yet.", ""]
        out.write_text("\n".join(lines))
        return
    have = {(r.experiment, r.arm, r.seed) for r in runs}
    requested = _requested(runs_dir) or [
        (e, a, sd) for sd in seeds for e in EXPERIMENTS for a in ARMS
    ]
    missing = [f"{e}/{a}/seed{sd}" for e, a, sd in requested if (e, a, sd) not in have]
    if missing:
        lines += [
            f"> **Incomplete grid**: {len(missing)} of {len(requested)}"
            " runs (experiment/arm/seed) did not finish in the session and are left out: "
            + ", ".join(missing)
            + ". The tables give the number of seeds per arm; `experiments/reproduce.sh` "
            "resumes and runs only these.",
            "",
        ]
    if "quick" in profiles:
        lines += [
            "> **Quick (smoke-test) profile**: tiny budgets, 1 seed. These numbers say "
            "nothing about the method.",
            "",
        ]
    sections: list[str] = []
    results: dict[str, dict[str, Any]] = {}
    for exp_name in EXPERIMENTS:
        exp_runs = [r for r in runs if r.experiment == exp_name]
        sec, res = _experiment_section(exp_name, exp_runs, plots_rel, plots_dir)
        sections += sec
        results[exp_name] = res

    lines += ["## Answer", ""]
    lines += _answer(results, runs)
    lines += ["## Summary per experiment", ""]
    lines += [_agreement(e, results[e]) for e in EXPERIMENTS]
    lines += [""]
    lines += sections

    # How it was run.
    all_invs = [i for i in _invocations(runs_dir) if i.get("runs_todo")]
    interrupted = [i for i in all_invs if i.get("interrupted")]
    starts = sorted(i["started_utc"] for i in all_invs if "started_utc" in i)
    ends = sorted(i["finished_utc"] for i in all_invs if "finished_utc" in i)
    elapsed = f"between {starts[0]} and {ends[-1]}" if starts and ends else "times unknown"
    busy_min = _busy_minutes(all_invs)
    run_wall = sum(float(r.meta.get("wall_time_s", 0)) for r in runs)
    total_steps = sum(int(r.meta.get("total_steps", 0)) for r in runs)
    commands = sorted({i["command"] for i in all_invs})
    vers = runs[0].meta.get("versions", {})
    diff_versions = sorted({json.dumps(r.meta.get("versions", {}), sort_keys=True) for r in runs})
    lines += [
        "## How this was run",
        "",
        f"- Profile(s): {', '.join(profiles)}; seeds {seeds[0]}..{seeds[-1]} "
        f"({len(seeds)}); {len(runs)} finished runs.",
        "- The one command: `experiments/reproduce.sh` (from the repository root; it runs "
        "the grid, then this report). The grid invocation(s) it made (resumable; finished "
        "runs are skipped):",
        "",
        *[f"      {c}" for c in commands],
        "",
        f"  then `python -m tamrm_experiments report --runs {runs_dir} --out {out}`.",
        f"- Wall time: {busy_min:.0f} min with at least one grid invocation running "
        f"({elapsed}, in one or more sessions) over {len(all_invs)} grid "
        "invocation(s), some of them concurrent (sharing the runs directory); "
        f"{len(interrupted)} of them were interrupted and "
        "restarted (to change a budget or the number of jobs: a run whose settings changed "
        "was redone, finished runs with unchanged settings were kept). Sum of the wall times "
        f"of the {len(runs)} runs reported: {run_wall / 60:.1f} min; "
        f"{total_steps:,} environment steps, each one gRPC round trip.",
        "- Versions: " + ", ".join(f"{k} {v}" for k, v in sorted(vers.items())) + ".",
    ]
    lines += [
        "",
        "Throughput (each step is one shaping round trip; the machine has "
        f"{vers.get('cpu_count', '?')} cores, shared with other work during part of the run):",
        "",
        "| experiment | runs | environment steps | sum of run wall times | steps/s per run |",
        "|---|---|---|---|---|",
    ]
    for exp_name, exp in EXPERIMENTS.items():
        rs = [r for r in runs if r.experiment == exp_name]
        if not rs:
            continue
        steps = sum(int(r.meta.get("total_steps", 0)) for r in rs)
        secs = sum(float(r.meta.get("wall_time_s", 0)) for r in rs)
        rate = t_interval([float(r.meta.get("steps_per_s") or math.nan) for r in rs])
        lines.append(
            f"| {exp.title} | {len(rs)} | {steps:,} | {secs / 60:.1f} min | "
            f"{_fmt_interval(rate, '{:,.0f}')} |"
        )
    lines.append("")
    if len(diff_versions) > 1:
        varying = {}
        for r in runs:
            for k, v in r.meta.get("versions", {}).items():
                varying.setdefault(k, set()).add(str(v))
        parts = [f"{k}: {', '.join(sorted(v))}" for k, v in sorted(varying.items()) if len(v) > 1]
        lines.append(
            "- Versions that differ between runs (the repository's HEAD moved while other "
            "work was committed; the server binary and the packages are what count): "
            + "; ".join(parts)
            + "."
        )
        if len(varying.get("tamrm_server_sha256", ())) > 1:
            lines.append(
                "- More than one server build served these runs (the binary was rebuilt as "
                "the code moved on): `git log -- src proto` between the runs' commits says "
                "what changed."
            )
    lines += ["", "## Deviations from the paper", ""]
    lines += [f"- {d}" for d in DEVIATIONS]
    lines += ["", "## Reading these results", ""]
    lines += [f"- {r}" for r in READING]
    lines += [""]
    lines += _closing(results, len(seeds))
    out.write_text("\n".join(lines))


MetricFn = Callable[[Run], float]
