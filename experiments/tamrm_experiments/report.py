"""Turn the raw per-episode CSVs into ``docs/reproduction.md`` and its plots.

Everything in the page is computed from the runs directory: the tables, the verdicts
and the closing note. Nothing is typed in by hand except the paper's own figures and
the list of deviations from the paper (which describe the setup, not the results).
"""

from __future__ import annotations

import functools
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tamrm_experiments.args import parser
from tamrm_experiments.configs import ARMS, EXPERIMENTS, make_specs, runs_variant
from tamrm_experiments.envs import (
    MAZE_NEW_START,
    MAZE_START,
    maze_shortest_path,
    random_policy_steps,
)
from tamrm_experiments.experiments.base import Claim, Metric
from tamrm_experiments.stats import (
    Interval,
    fisher_p,
    holm,
    rolling_mean,
    t_interval,
    welch_interval,
    welch_p,
)

__all__ = [
    "Analysis",
    "Run",
    "analyse",
    "load_runs",
    "readme_summary",
    "run_metrics",
    "update_readme",
    "write_report",
]


@dataclass
class Run:
    """One finished run: its sidecar and its per-episode rows."""

    experiment: str
    arm: str
    seed: int
    meta: dict[str, Any]
    df: pd.DataFrame
    variant: str = "clean"
    fidelity: str = "clean"

    @property
    def budget(self) -> dict[str, Any]:
        """The run's budget (episodes, caps)."""
        return dict(self.meta["spec"]["budget"])

    @property
    def backend(self) -> str:
        """Where its shaping was computed: ``engine`` (embedded, in process) or ``server``
        (over gRPC; every run recorded before the engine, whose sidecar has no key)."""
        return str(self.meta.get("backend", "server"))


def load_runs(runs_dir: Path) -> list[Run]:
    """Load every complete run under ``runs_dir`` (any depth: ``<experiment>/<variant>/
    <arm>/seedN``; runs of the first report, without a variant, count as ``clean``)."""
    runs = []
    for meta_path in sorted(runs_dir.rglob("seed*.json")):
        try:
            meta = json.loads(meta_path.read_text())
        except ValueError:
            continue
        csv_path = meta_path.with_suffix(".csv")
        if not meta.get("complete") or not csv_path.is_file():
            continue
        spec = meta["spec"]
        runs.append(
            Run(
                spec["experiment"],
                spec["arm"],
                spec["seed"],
                meta,
                pd.read_csv(csv_path),
                spec.get("variant", "clean"),
                spec.get("fidelity", "clean"),
            )
        )
    return runs


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
        x, mean, low, high = _curves(arm_runs, window, log=exp.plot_log)
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


def _requested(runs_dir: Path) -> list[tuple[str, str, str, int]]:
    """(experiment, variant, arm, seed) of every run that some grid invocation asked for,
    in grid order: each invocation's recorded command line parsed as the ``run`` command
    does (a command line without ``--profile`` is read with the default of its time,
    ``full``, if it has no ``--fidelity``/``--variants``: the first report's)."""
    import shlex

    keys: dict[tuple[str, str, str, int], None] = {}
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
        profile = args.profile or ("quick" if args.quick else "paper")
        for spec in make_specs(
            profile,
            args.seeds,
            args.experiments,
            args.arms,
            args.first_seed,
            args.fidelity,
            args.variants,
        ):
            keys[(spec.experiment, spec.variant, spec.arm, spec.seed)] = None
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
    exp_name: str, runs: list[Run], plots_rel: str, plots_dir: Path, variant: str = "clean"
) -> tuple[list[str], dict[str, Any]]:
    exp = EXPERIMENTS[exp_name]
    var = exp.variant(variant)
    title = f"{exp.short}: {var.label}"
    lines = [f"## {title}", ""]
    if not runs:
        return [*lines, "No finished runs.", ""], {}
    metrics = {arm: [] for arm in ARMS}  # type: dict[str, list[dict[str, float]]]
    censored = {arm: 0 for arm in ARMS}
    for r in runs:
        metrics[r.arm].append(run_metrics(r))
        censored[r.arm] += int(bool(r.meta.get("censored")))
    lines.append(f"Budget: {_budget_line(exp_name, runs)}.")
    owner = runs_variant(exp, variant, "plain")
    if owner != variant:
        lines.append(
            f"The plain arm is shared with *{exp.variant(owner).label}* (the same runs): "
            "the variants differ only in shaping settings, which plain does not use."
        )
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
    png = plots_dir / f"{exp_name}-{variant}.png"
    plot_experiment(exp_name, runs, png, title)
    lines.append(f"![{title}]({plots_rel}/{png.name})")
    lines.append("")
    return lines, {"metrics": metrics, "comparisons": comps, "censored": censored}


def _diagnostics(runs: list[Run]) -> list[str]:
    """Per arm: how much each shaping term contributed, per step."""
    lines = [
        "Shaping diagnostics (mean over seeds of per-run totals / steps): the kNN reward "
        "r(t) and the potential term F as computed by tamrm, before the weights "
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
    "estimate (actor-critic and A2C: V(s); DQN: max_a Q(s, a)). With the learner's gamma, "
    "F = gamma V(s') - V(s) is delta - R, where delta = R + gamma V(s') - V(s) is the TD "
    "error of the current estimate, so R + beta F = (1 - beta) R + beta delta (exactly "
    "so for the actor-critic; for the authors' DQN, whose V(s') comes from the target "
    "network, nearly). Phi also moves as the network learns, so Ng et al.'s guarantee "
    "that potential-based shaping keeps the optimal policy (a fixed Phi) does not apply. "
    "Gating it to the kNN window (`gate_potential`, the authors' code) confines this to "
    "the steps N <= t < L_min.",
    "**The kNN term rewards agreeing with stored action sequences at the same time "
    "index.** r(t) lies in [1 - e^0.5, e - e^0.5] = [-0.65, +1.07], of the size of the "
    "environment reward in cart pole and mountain car and far larger than the maze's "
    "(0 except at the goal). It is not potential-based, so it can change which policy "
    "is optimal. With a fixed start (the authors' cart pole) an action prefix identifies "
    "the state, so imitating a stored open-loop sequence can work; with random starts it "
    "cannot. In the maze one detour shifts every later index, so a later prefix rarely "
    "matches a stored path (*kNN active* in the diagnostics).",
    "**Many comparisons.** The claims table adjusts its p-values with Holm's method over "
    "all its tests; the per-variant sections below give unadjusted 95% intervals, of "
    "which about one in twenty excludes zero by chance alone.",
    "**Two fidelities answer two questions.** *Authors*: does the method help the "
    "learners it was published with, in their settings? *Clean*: does it help standard, "
    "reasonably tuned learners? A stronger baseline leaves less room for shaping.",
]

DEVIATIONS = [
    "**Authors fidelity**: the learners of the authors' code transcribed into numpy "
    "(`tamrm_experiments/learners.py`: one-step actor-critic for cart pole, 1x20 ReLU, "
    "Adam 1e-3 actor / 1e-2 critic, gamma 0.9, the actor's learning rate dropped to 1e-5 "
    "once the mean of 100 episodes reaches 195; tutorial DQN for mountain car, 1x20 ReLU, "
    "RMSProp 0.005, MSE, gamma 0.9, learning only once 50 000 steps were taken, target "
    "copied every 500 learning steps, epsilon 1 -> 0.1 by 5e-5 per learning step), their "
    "episode loops (`tamrm_experiments/authors.py`) and their shaping settings, computed "
    "by tamrm: both terms only while the pool is full and N <= t < L_min "
    "(`gate_potential` on; PBRS-only arm: their ungated PBRS line), their terminal "
    "overrides after the shaping (cart pole: -1 on failure; mountain car: +10 at the "
    "goal), the episode score = the sum of the environment rewards.",
    "Authors' cart pole: unwrapped `CartPole-v1` (pole limit 12 degrees), episodes cut at "
    "200 steps, pool 30, k 20, N 8, alpha = beta = 0.8 (PBRS only: beta 1). *Fixed "
    "start*: the environment is reseeded before every reset (theirs: `env.seed(2)`; ours: "
    "the run's seed, so each seed has its own start state); *random start*: seeded once.",
    "Authors' mountain car: unwrapped `MountainCar-v0` (no 200-step limit), safety caps of "
    "100 000 steps per episode and 3 000 000 per run (never reached by their saved runs), "
    "pool 20, k 20, N 10, gamma 0.9, potential from max Q(s) of the online and "
    "max Q(s') of the target network (theirs); *their signs* alpha = beta = -1 (their "
    "code subtracts both terms) and *the paper's* +1.",
    "What remains different from the authors' code (tamrm follows SPEC.md): their "
    "window ends one step earlier (t < L_min - 1); their pool also replaces the worst "
    "trajectory on a tie; their distances add 0.001 to every component and they round "
    "f(t) to 4 decimals (`experiments/tests/test_authors_formula.py` checks r(t) against a "
    "transcription of their `predict_modified`); F of a terminal step uses V(s') = 0 "
    "(theirs: the network's value), which the terminal overrides make irrelevant; they "
    "ran one seed, we run seeds 0..N-1 (network initialisation, action sampling, "
    "environment).",
    "Authors' maze (`Maze_grid/run_maze.py`): the same layout, start and goal as ours; "
    "the observation is the agent's 4 canvas coordinates; their DQN (10 hidden units, "
    "Adam 0.01, greedy 0.9 from the start, learning once 20 000 steps were taken, target "
    "every 200); both terms while the pool is full and 8 <= t < L_min (their `predict`: "
    "every stored trajectory weighted, k = |D|, alpha 0.8, beta 0.3; PBRS only: beta 1); "
    "+1 at the goal, -1 on the time-out at 10 000 steps, score +-100/t; |D| = 3 (their "
    "run) and 10 (the paper); *bug*: their script's `ob_ = ob`, so the agent always sees "
    "the start cell (as their saved results ran), and without it.",
    "Authors' maze, *tuned*: their DQN does not learn the maze in 200 episodes even "
    "without the bug (plain ~500-800 steps per episode at the end, a random walk's 817), "
    "so the maze claims cannot be tested on it. The pilot (`docs/reproduction/"
    "maze-pilot.md`, `python -m tamrm_experiments.pilot`) found three changes needed "
    "together: the cell one-hot (64 inputs) instead of the pixel coordinates, 64 hidden "
    "units, epsilon 1 -> 0.1 by 1e-4 per learning step; and learning from step 1 000 "
    "instead of 20 000 (a random start twice as long as a learning run). Everything else "
    "(loop, window, gating, signs, overrides) is theirs.",
    "Shared plain arms: variants that differ only in what the shaping terms alone read "
    "(signs, PBRS-only beta, `gate_potential`, the kNN pool) share one set of plain runs "
    "(`Variant.plain_from`): mountain car's paper's signs use their signs' plain runs, "
    "`clean-gated` uses `clean`'s, the maze's pool of 10 its pool of 3's.",
    "**Clean fidelity**: Stable-Baselines3 learners on `tamrm.sb3.ShapedVecEnv` (one "
    "call to tamrm per environment step, the potential from the model's own estimates: "
    "A2C critic V(s), DQN max_a Q(s, a) of the online network), the service's defaults "
    "(N = 10, min_pool_size = pool capacity) and two variants: `gate_potential` off (as "
    "the first report ran) and on.",
    "Clean cart pole: SB3 A2C (actor and critic 2x20, SB3 defaults: lr 7e-4, n_steps 5, "
    "gamma 0.99, RMSprop), `CartPole-v0` (200-step episodes), reward +1 per step and -1 "
    "on the failing step; pool 30, k 20, alpha = beta = 0.8, gamma 0.99.",
    "Clean mountain car: SB3 DQN 2x20, lr 0.005, fixed epsilon 0.1, gamma 0.9, batch 32, "
    "learning from step 200, a gradient step every 4 steps, target copied every 200; "
    "`MountainCar-v0` without the 200-step limit, capped at 10 000 steps per episode; "
    "pool 20, k 20, alpha = beta = 1.",
    "Clean maze: the first report's DQN on the raw (x, y) cell did not learn the maze "
    "(plain ~900 steps per episode after 200 episodes, a random walk's ~817). It is "
    "replaced (issue 14's pilot) by SB3 DQN on a one-hot cell (64 inputs, one hidden "
    "layer of 64, lr 1e-3, gamma 0.9, a gradient step on every step from step 500, target "
    "copied every 500, epsilon 1 -> 0.05 over the first 10 000 steps); pool 10, k 10, "
    "alpha 0.8, beta 0.3. Episode score 100/steps on success, 0 on a truncated failure. "
    f"Start {MAZE_START} (shortest path {maze_shortest_path(MAZE_START)} moves).",
    "Modified maze: after 100 episodes (the paper's) the start moves to "
    f"{MAZE_NEW_START} (our choice; shortest path {maze_shortest_path(MAZE_NEW_START)} "
    "moves); every arm, plain included, continues on a new task id (a fresh pool); the "
    "DQN keeps its network and replay buffer.",
    "Every arm, plain included, goes through tamrm (plain: alpha = beta = 0), so "
    "that every arm runs the same loop; kNN only (beta = 0) is the ablation the paper "
    "lacks. Each run has a safety cap on its total steps; a run reaching it is reported "
    "as censored (its totals are lower bounds, marked ≥).",
]


# -- the claims table ------------------------------------------------------------------

Group = tuple[str, str]  # (experiment, variant)


@dataclass
class ClaimRow:
    """One claim measured in one variant."""

    exp_name: str
    variant: str
    claim: Claim
    arm_values: list[float]
    plain_values: list[float]
    planned: int  # seeds per arm asked for (by some invocation)
    diff: Interval = field(default_factory=lambda: Interval(math.nan, math.nan, math.nan, 0))
    p: float = math.nan
    p_holm: float = math.nan
    censored: bool = False

    @property
    def test_key(self) -> tuple[Any, ...]:
        """What the test reads: its metric and its two samples."""
        return (self.claim.metric, tuple(self.arm_values), tuple(self.plain_values))

    @property
    def complete(self) -> bool:
        """Every requested seed of both arms is done."""
        n = min(len(self.arm_values), len(self.plain_values))
        return n >= self.planned > 0

    def measure(self) -> None:
        """The interval of (arm - plain) and the unadjusted p-value."""
        self.diff = welch_interval(self.arm_values, self.plain_values)
        if self.claim.metric == "solved":
            k_a, k_p = int(sum(self.arm_values)), int(sum(self.plain_values))
            self.p = fisher_p(k_a, len(self.arm_values), k_p, len(self.plain_values))
        else:
            self.p = welch_p(self.arm_values, self.plain_values)

    def judge(self) -> tuple[str, str]:
        """(word, kind): the verdict's word and which case of it, one of ``too-few``,
        ``censored``, ``holds``, ``opposite``, ``pending``, ``claimed-way``,
        ``other-way`` (the last two: unadjusted p < 0.05, not after Holm) and ``none``."""
        n_a, n_p = len(self.arm_values), len(self.plain_values)
        if n_a < 2 or n_p < 2:
            return "cannot be decided yet", "too-few"
        sig = not math.isnan(self.p_holm) and self.p_holm < 0.05
        if sig and self.sign == self.claim.direction:
            if self.censored and self.claim.direction == -1:
                return "cannot be decided yet", "censored"
            return "holds", "holds"
        if sig:
            return "does not hold", "opposite"
        if not self.complete:
            return "cannot be decided yet", "pending"
        if not math.isnan(self.p) and self.p < 0.05:
            way = "claimed-way" if self.sign == self.claim.direction else "other-way"
            return "does not hold", way
        return "does not hold", "none"

    @property
    def sign(self) -> int:
        """The sign of the estimated (arm - plain): -1, 0 or +1."""
        return 0 if math.isnan(self.diff.mean) else (1 if self.diff.mean > 0 else -1)

    @property
    def seeds(self) -> int:
        """Seeds done in both arms."""
        return min(len(self.arm_values), len(self.plain_values))

    def verdict(self) -> tuple[str, str]:
        """(word, why): ``holds``, ``does not hold`` or ``cannot be decided yet``."""
        word, kind = self.judge()
        n = self.seeds
        if kind == "too-few":
            n_a, n_p = len(self.arm_values), len(self.plain_values)
            return word, f"{n_a} and {n_p} of {self.planned} seeds done"
        if kind == "censored":
            return word, "significant, but some totals are lower bounds"
        if kind == "holds":
            return word, f"Holm-adjusted p = {self.p_holm:.3g}"
        if kind == "opposite":
            return word, (
                f"significant in the opposite direction (Holm-adjusted p = {self.p_holm:.3g})"
            )
        hint = ""
        if not math.isnan(self.p) and self.p < 0.05:
            hint = f"; unadjusted p = {self.p:.2g}, " + (
                "in the claimed direction" if self.sign == self.claim.direction else "the other way"
            )
        if kind == "pending":
            return word, (
                f"no significant difference with {n} of {self.planned} seeds "
                "done (Holm-adjusted p = "
                f"{self.p_holm:.2g}{hint})"
            )
        if kind == "claimed-way":
            # A large but variable effect: say so rather than call it small.
            return word, (
                f"no significant difference at {n} seeds after Holm's correction "
                f"(Holm-adjusted p = {self.p_holm:.2g}{hint}): the estimate points the claimed "
                "way, but the seeds vary too much for it to survive the correction for the "
                "table's tests"
            )
        return word, (
            f"no significant difference at {n} seeds (Holm-adjusted p = "
            f"{self.p_holm:.2g}{hint}): any effect in the claimed direction is smaller than "
            "these seeds resolve"
        )

    def short_verdict(self) -> str:
        """The verdict in a few words, for the README's summary."""
        word, kind = self.judge()
        why = {
            "too-few": f"{self.seeds} of {self.planned} seeds done",
            "censored": "significant, but some totals are lower bounds",
            "holds": "",
            "opposite": "significant the other way",
            "pending": f"{self.seeds} of {self.planned} seeds done",
            "claimed-way": "the claimed way, not significant after Holm",
            "other-way": "the other way, not significant after Holm",
            "none": "no significant difference",
        }[kind]
        return f"**{word}**" + (f": {why}" if why else "")

    def cell(self) -> str:
        """The measured cell: both arms, the difference, the test."""
        fmt = "{:,.2f}" if self.claim.metric == "solved" else "{:,.1f}"
        if self.claim.metric == "solved":
            parts = [
                f"{self.claim.arm} {int(sum(self.arm_values))}/{len(self.arm_values)}, "
                f"plain {int(sum(self.plain_values))}/{len(self.plain_values)} seeds solved"
            ]
        else:
            a, p = t_interval(self.arm_values), t_interval(self.plain_values)
            parts = [f"{self.claim.arm} {_fmt_interval(a, fmt)}, plain {_fmt_interval(p, fmt)}"]
        if self.claim.metric == "solved":
            if not math.isnan(self.p):
                parts.append(f"Fisher p = {self.p:.2g}, Holm {self.p_holm:.2g}")
        elif not math.isnan(self.diff.low):
            parts.append(
                f"difference {_fmt(self.diff.mean, fmt)} [{_fmt(self.diff.low, fmt)}, "
                f"{_fmt(self.diff.high, fmt)}], p = {self.p:.2g}, Holm {self.p_holm:.2g}"
            )
        prefix = "≥ " if self.censored and self.claim.metric in CENSORABLE else ""
        return prefix + "; ".join(parts)


def _claim_rows(
    groups: dict[Group, list[Run]], requested: list[tuple[str, str, str, int]]
) -> list[ClaimRow]:
    rows = []
    for (exp_name, variant), runs in groups.items():
        exp = EXPERIMENTS[exp_name]
        for claim in exp.claims:
            by_arm = {arm: [r for r in runs if r.arm == arm] for arm in (claim.arm, "plain")}
            planned = min(
                len(_wanted(requested, exp_name, variant, arm)) for arm in (claim.arm, "plain")
            )
            asked = {
                arm for arm in (claim.arm, "plain") if _wanted(requested, exp_name, variant, arm)
            }
            if not by_arm[claim.arm] and claim.arm not in asked:
                continue  # this arm is not part of the grid asked for
            done = min(len(by_arm[claim.arm]), len(by_arm["plain"]))
            row = ClaimRow(
                exp_name,
                variant,
                claim,
                [run_metrics(r)[claim.metric] for r in by_arm[claim.arm]],
                [run_metrics(r)[claim.metric] for r in by_arm["plain"]],
                max(planned, done),
                censored=any(r.meta.get("censored") for rs in by_arm.values() for r in rs),
            )
            row.measure()
            rows.append(row)
    _adjust(rows)
    return rows


def _adjust(rows: list[ClaimRow]) -> None:
    """Holm-adjust the rows' p-values together, each distinct test once: rows whose two
    samples are equal value by value (e.g. the authors' maze PBRS-only arm, which reads
    neither the pool nor k, so pool 3 and pool 10 run identically) are one hypothesis
    tested once, and share its adjusted p-value."""
    slot: dict[tuple[Any, ...], int] = {}
    for row in rows:
        slot.setdefault(row.test_key, len(slot))
    p_of = {slot[row.test_key]: row.p for row in rows}  # equal samples, equal p
    adjusted = holm([p_of[i] for i in range(len(slot))])
    for row in rows:
        row.p_holm = adjusted[slot[row.test_key]]


def _distinct_tests(rows: list[ClaimRow]) -> int:
    """How many distinct tests (see :func:`_adjust`) with a p-value the rows hold."""
    return len({row.test_key for row in rows if not math.isnan(row.p)})


def _claims_table(rows: list[ClaimRow]) -> list[str]:
    from tamrm_experiments.authors_data import authors_summary

    lines = [
        "One row per claim of the paper and variant of ours. *Ours* cells: mean over seeds "
        "[95% t-interval] per arm, the Welch 95% interval of (arm - plain), the unadjusted "
        "p-value (Welch's t-test; Fisher's exact test for seeds solved) and the "
        f"Holm-adjusted one over the {_distinct_tests(rows)} distinct tests of this table "
        "(rows whose runs are identical, such as the authors' maze PBRS-only arm, which "
        "reads neither the pool nor k, are one test). A claim *holds* if the adjusted "
        "p < 0.05 in the claimed direction, "
        "*does not hold* if it is significant the other way or if every planned seed is "
        "done without a significant difference, and *cannot be decided yet* otherwise.",
        "",
        "| claim | paper | authors' saved runs | variant | ours | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        exp = EXPERIMENTS[row.exp_name]
        word, why = row.verdict()
        lines.append(
            f"| {exp.short}: {row.claim.text} | {row.claim.paper} | "
            f"{authors_summary(row.exp_name) or '-'} | {exp.variant(row.variant).label} | "
            f"{row.cell()} | **{word}**: {why} |"
        )
    lines.append("")
    return lines


# -- shared plain arms -----------------------------------------------------------------


def _wanted(
    requested: list[tuple[str, str, str, int]], exp_name: str, variant: str, arm: str
) -> list[int]:
    """The seeds of ``arm`` in ``variant`` that some invocation asked for: for a shared
    plain arm, those of the variant whose plain runs it uses."""
    owner = runs_variant(EXPERIMENTS[exp_name], variant, arm)
    return sorted({sd for e, v, a, sd in requested if (e, v, a) == (exp_name, owner, arm)})


def _groups(runs: list[Run], requested: list[tuple[str, str, str, int]]) -> dict[Group, list[Run]]:
    """The runs of each (experiment, variant) asked for or run: its own arms, and for the
    plain arm the runs of the variant it shares plain with (``Variant.plain_from``). A
    variant's own plain runs made before it shared them are left out (see
    ``_shared_plain``)."""
    groups: dict[Group, list[Run]] = {}
    for exp_name, exp in EXPERIMENTS.items():
        for var in exp.variants:
            rs = [
                r
                for r in runs
                if r.experiment == exp_name and r.variant == runs_variant(exp, var.name, r.arm)
            ]
            asked = any((e, v) == (exp_name, var.name) for e, v, _a, _s in requested)
            # Another variant's plain runs alone do not make a section.
            if asked or any(r.variant == var.name for r in rs):
                groups[(exp_name, var.name)] = rs
    return groups


#: Columns of a run's CSV that a rerun with the same seed reproduces (not the wall time,
#: nor the shaping diagnostics, which depend on the variant's pool settings).
REPLAYED = ("episode", "steps", "env_return", "terminated", "truncated", "success", "score")


def _shared_plain(groups: dict[Group, list[Run]], runs: list[Run]) -> list[str]:
    """Which variants share a plain arm, and whether a variant's own plain runs from
    before the sharing agree, episode by episode, with the shared runs of the same seed."""
    lines = []
    for exp_name, variant in groups:
        exp = EXPERIMENTS[exp_name]
        owner = runs_variant(exp, variant, "plain")
        if owner == variant:
            continue
        own = [r for r in runs if (r.experiment, r.variant, r.arm) == (exp_name, variant, "plain")]
        shared = {
            r.seed: r
            for r in runs
            if (r.experiment, r.variant, r.arm) == (exp_name, owner, "plain")
        }
        same = [r.seed for r in own if r.seed in shared and _replays(r, shared[r.seed])]
        differ = [r.seed for r in own if r.seed in shared and r.seed not in same]
        text = (
            f"- {exp.short}, {exp.variant(variant).label}: the plain arm is the runs of "
            f"*{exp.variant(owner).label}* (the variants differ only in shaping settings, "
            "which the plain arm does not use)."
        )
        if own:
            text += (
                f" Earlier plain runs of its own (seeds {_seed_list(sorted(r.seed for r in own))}"
                f"), kept in the raw data: {len(same)} identical episode by episode to the shared "
                f"run of the same seed, {len(differ)} different"
                + (f" (seeds {_seed_list(differ)})" if differ else "")
                + ", "
                + f"{len(own) - len(same) - len(differ)} without a shared run to compare."
            )
        lines.append(text)
    if not lines:
        return []
    return [
        "Shared plain arms: the plain arm does not depend on the shaping signs or the "
        "gate, so it runs once per set of such variants.",
        "",
        *lines,
        "",
    ]


def _replays(a: Run, b: Run) -> bool:
    """Whether two runs have the same episodes (``REPLAYED`` columns)."""
    cols = [c for c in REPLAYED if c in a.df.columns and c in b.df.columns]
    return len(a.df) == len(b.df) and a.df[cols].reset_index(drop=True).equals(
        b.df[cols].reset_index(drop=True)
    )


# -- status, pilot, cost ---------------------------------------------------------------


def _partials(runs_dir: Path) -> dict[tuple[str, str, str, int], int]:
    """Runs in progress (or interrupted): episodes written so far."""
    out = {}
    for path in runs_dir.rglob("seed*.csv.partial"):
        rel = path.relative_to(runs_dir).parts
        if len(rel) != 4:
            continue
        seed = int(rel[3].removeprefix("seed").split(".")[0])
        with open(path) as fh:
            out[(rel[0], rel[1], rel[2], seed)] = max(0, sum(1 for _ in fh) - 1)
    return out


def _status(
    groups: dict[Group, list[Run]],
    requested: list[tuple[str, str, str, int]],
    partial: dict[tuple[str, str, str, int], int],
) -> list[str]:
    lines = [
        "| experiment | variant | arm | seeds done | pending (requested, not finished) |",
        "|---|---|---|---|---|",
    ]
    for (exp_name, variant), runs in groups.items():
        exp = EXPERIMENTS[exp_name]
        for arm in ARMS:
            done = sorted(r.seed for r in runs if r.arm == arm)
            want = _wanted(requested, exp_name, variant, arm)
            pending = [sd for sd in want if sd not in done]
            if not done and not pending:
                continue
            owner = runs_variant(exp, variant, arm)
            pend = []
            for sd in pending:
                eps = partial.get((exp_name, owner, arm, sd))
                pend.append(f"{sd} ({eps} episodes so far)" if eps else str(sd))
            shared = f" (the runs of {owner})" if owner != variant else ""
            lines.append(
                f"| {exp.short} | {exp.variant(variant).label} | {ARMS[arm].label}{shared} | "
                f"{len(done)}: {_seed_list(done)} | {len(pending)}"
                + (f": {', '.join(pend)}" if pend else "")
                + " |"
            )
    lines.append("")
    return lines


def _seed_list(seeds: list[int]) -> str:
    if not seeds:
        return "-"
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _pilot(groups: dict[Group, list[Run]]) -> list[str]:
    """Does the plain learner learn within the budget? First vs last episodes, and the
    last episodes vs a uniformly random policy."""
    lines = [
        "Plain learner per variant: mean steps per episode over the first and the last 20 "
        "episodes of each seed (mean [95% t-interval] over seeds), beside a uniformly random "
        "policy's mean steps per episode under the same cap (maze: the exact random walk, "
        f"from {MAZE_START}, shortest path {maze_shortest_path(MAZE_START)}; modified maze: "
        f"from the new start {MAZE_NEW_START}, where its last episodes start; mountain car "
        "and cart pole: 2000 simulated episodes). In cart pole more is better (200 = kept up "
        "for the whole episode), elsewhere fewer. *Learns* if the last 20 episodes are "
        "detectably better (their interval clear of the other) than the first 20 or than "
        "the random policy.",
        "",
        "| experiment | variant | seeds | first 20 episodes | last 20 episodes "
        "| random policy | learns? |",
        "|---|---|---|---|---|---|---|",
    ]
    for (exp_name, variant), runs in groups.items():
        plain = [r for r in runs if r.arm == "plain" and len(r.df) >= 40]
        if not plain or any(r.variant != variant for r in plain):
            continue  # none, or another variant's plain runs (listed under that variant)
        exp = EXPERIMENTS[exp_name]
        pilot = _plain_learns(exp_name, plain)
        lines.append(
            f"| {exp.short} | {exp.variant(variant).label} | {len(plain)} | "
            f"{_fmt_interval(pilot.first, '{:,.1f}')} | {_fmt_interval(pilot.last, '{:,.1f}')} "
            f"| {pilot.random_policy:,.1f} | {pilot.verdict} |"
        )
    lines.append("")
    return lines


@dataclass(frozen=True)
class Pilot:
    """Whether a variant's plain learner learns: its first and last 20 episodes (mean steps
    per episode, t-intervals over seeds), a random policy's mean, and the verdict."""

    first: Interval
    last: Interval
    random_policy: float
    verdict: str


@functools.cache
def _random_policy(exp_name: str, max_steps: int, after_switch: bool) -> float:
    """:func:`random_policy_steps`, once per report for each experiment and cap."""
    return random_policy_steps(exp_name, max_steps, after_switch)


def _plain_learns(exp_name: str, plain: list[Run]) -> Pilot:
    """The pilot of ``plain`` (runs of at least 40 episodes): ``yes`` if the last 20
    episodes are detectably better than the first 20 or than a random policy, else ``not
    detectably`` (``n=1`` for a single seed)."""
    plain = [r for r in plain if len(r.df) >= 40]
    first = t_interval([float(r.df["steps"].head(20).mean()) for r in plain])
    last = t_interval([float(r.df["steps"].tail(20).mean()) for r in plain])
    budget = plain[0].budget
    random_policy = _random_policy(
        exp_name, int(budget["max_episode_steps"]), budget.get("switch_after") is not None
    )
    if math.isnan(last.low):
        return Pilot(first, last, random_policy, "n=1")
    if EXPERIMENTS[exp_name].headline == "mean_steps":  # more steps kept up is better
        better = last.low > first.high or last.low > random_policy
    else:
        better = last.high < first.low or last.high < random_policy
    return Pilot(first, last, random_policy, "yes" if better else "not detectably")


def _backends(runs: list[Run]) -> str:
    """The runs' backends, counted: ``server``, or ``engine 3, server 10`` when mixed."""
    counts = Counter(r.backend for r in runs)
    if len(counts) == 1:
        return next(iter(counts))
    return ", ".join(f"{b} {n}" for b, n in sorted(counts.items()))


def _cost(groups: dict[Group, list[Run]], requested: list[tuple[str, str, str, int]]) -> list[str]:
    lines = [
        "Cost per run (each environment step is one call to tamrm: in process on the "
        "embedded engine, or a gRPC round trip to a local server, as the *backend* column "
        "says; 2 cores shared with other work, runs under `nice`), and what the pending runs "
        "of each variant would cost at that rate (one run per core; runs in progress count "
        "whole):",
        "",
        "| experiment | variant | runs | backend | steps per run | wall time per run | steps/s "
        "| pending runs | their estimated cost |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    total_pending = 0.0
    for (exp_name, variant), runs in groups.items():
        exp = EXPERIMENTS[exp_name]
        # Shared plain runs count once, under the variant that owns them.
        done = {(r.arm, r.seed) for r in runs if r.variant == variant}
        pending = [
            (a, sd)
            for e, v, a, sd in requested
            if (e, v) == (exp_name, variant) and (a, sd) not in done
        ]
        if not runs and not pending:
            continue
        steps = t_interval([float(r.meta.get("total_steps", 0)) for r in runs])
        wall = t_interval([float(r.meta.get("wall_time_s", 0)) / 60 for r in runs])
        rate = t_interval([float(r.meta.get("steps_per_s") or math.nan) for r in runs])
        est = "-"
        if pending and runs:
            hours = len(pending) * wall.mean / 60
            total_pending += hours
            est = f"{hours:,.1f} core-hours"
        elif pending:
            est = "unknown (no finished run yet)"
        lines.append(
            f"| {exp.short} | {exp.variant(variant).label} | {len(runs)} | "
            f"{_backends(runs) if runs else '-'} | {_fmt_interval(steps, '{:,.0f}')} | "
            + (f"{_fmt_interval(wall, '{:,.1f}')} min" if runs else "-")
            + f" | {_fmt_interval(rate, '{:,.0f}')} | {len(pending)} | {est} |"
        )
    lines += ["", f"Pending runs with a measured cost: {total_pending:,.1f} core-hours.", ""]
    return lines


@dataclass
class Analysis:
    """Everything the report and the README's summary compute from the runs."""

    runs_dir: Path
    current: list[Run]  # the runs of ``runs_dir``
    earlier: list[Run]  # the first report's runs, as variant ``clean-v1``
    requested: list[tuple[str, str, str, int]]
    groups: dict[Group, list[Run]]
    rows: list[ClaimRow]

    @property
    def runs(self) -> list[Run]:
        """Current and earlier runs."""
        return self.current + self.earlier

    @property
    def progress(self) -> tuple[int, int]:
        """(finished, requested) runs of the current grid."""
        asked = set(self.requested)
        done = sum(1 for r in self.current if (r.experiment, r.variant, r.arm, r.seed) in asked)
        return done, len(self.requested) - len(self.earlier)


def analyse(runs_dir: Path, previous: Path | None = None) -> Analysis:
    """Load the runs (and the first report's, ``previous``: runs without a variant, shown
    as the ``clean-v1`` variant, complete as they stand) and measure every claim."""
    current = load_runs(runs_dir)
    earlier = []
    if previous is not None and previous.is_dir():
        for r in load_runs(previous):
            if "variant" not in r.meta["spec"]:
                r.variant = "clean-v1"
                earlier.append(r)
    requested = _requested(runs_dir) or [(r.experiment, r.variant, r.arm, r.seed) for r in current]
    requested += [(r.experiment, r.variant, r.arm, r.seed) for r in earlier]
    groups = _groups(current + earlier, requested)
    rows = _claim_rows(groups, requested) if current or earlier else []
    return Analysis(runs_dir, current, earlier, requested, groups, rows)


def write_report(
    runs_dir: Path, out: Path, plots_dir: Path, previous: Path | None = None
) -> Analysis:
    """Write the markdown page ``out`` and the plots into ``plots_dir``; return what it
    was computed from.

    ``previous``: a runs directory of the first report (runs without a variant), shown as
    the ``clean-v1`` variant: complete as it stands (nothing pending)."""
    an = analyse(runs_dir, previous)
    runs, current, earlier, groups = an.runs, an.current, an.earlier, an.groups
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        plots_rel = str(plots_dir.resolve().relative_to(out.parent.resolve()))
    except ValueError:
        plots_rel = str(plots_dir.resolve())
    lines = [
        "# Reproduction of the TAMRM paper's experiments",
        "",
        "*Generated by `python -m tamrm_experiments report` from the raw runs in "
        f"`{runs_dir}`"
        + (f" and the first report's runs in `{previous}`" if earlier else "")
        + "; do not edit by hand.*",
        "",
        "Question: does TAMRM shaping, served by tamrm, speed up learning as the paper "
        "claims? Every experiment runs in two fidelities, four arms each (plain, PBRS only, "
        "kNN only, TAMRM), several seeds: *authors* (the learners, environments, gating, "
        "signs and terminal overrides of the authors' published code, transcribed) and "
        "*clean* (Stable-Baselines3 learners, SPEC defaults, the potential term ungated and "
        "gated). tamrm computes every shaped reward: in process (its embedded engine) or "
        "on a server over gRPC, the same rewards either way (each run's backend: "
        "*How this was run*).",
        "",
    ]
    if not runs:
        lines += ["No finished runs yet.", ""]
        out.write_text("\n".join(lines))
        return an
    requested = an.requested
    profiles = sorted({r.meta["spec"]["profile"] for r in runs})
    if "quick" in profiles:
        lines += [
            "> **Quick (smoke-test) profile**: tiny budgets, 1 seed. These numbers say "
            "nothing about the method.",
            "",
        ]
    n_done, n_req = an.progress
    lines += [
        "## Claims",
        "",
        (
            f"All {n_req} runs of the grid are finished (status below)"
            if n_done == n_req
            else f"{n_done} of the {n_req} runs of the current grid asked for so far are "
            "finished (status below)"
        )
        + (f", besides the first report's {len(earlier)} runs" if earlier else "")
        + ("." if n_done == n_req else "; the grid is resumable and later sessions continue it."),
        "",
    ]
    lines += _claims_table(an.rows)
    lines += ["## Status of the grid", ""]
    lines += _status(groups, requested, _partials(runs_dir))
    lines += _shared_plain(groups, runs)
    lines += ["## Pilot: do the plain learners learn within the budget?", ""]
    lines += _pilot(groups)
    for (exp_name, variant), rs in groups.items():
        sec, _res = _experiment_section(exp_name, rs, plots_rel, plots_dir, variant)
        lines += sec
    lines += ["## How this was run", ""]
    lines += _how_run(runs_dir, current or runs, out, previous if earlier else None)
    lines += _cost(groups, requested)
    lines += ["## Settings and deviations from the paper", ""]
    lines += [f"- {d}" for d in DEVIATIONS]
    lines += ["", "## Reading these results", ""]
    lines += [f"- {r}" for r in READING]
    lines += [""]
    out.write_text("\n".join(lines))
    return an


# -- the README's summary --------------------------------------------------------------

#: The lines around the README's generated summary of the claims table.
README_BEGIN = (
    "<!-- reproduction summary: generated by `python -m tamrm_experiments report "
    "--readme README.md` from the raw runs; do not edit by hand -->"
)
README_END = "<!-- end of the reproduction summary -->"


def _short_fmt(*values: float) -> str:
    """One format for a row's numbers: no decimals once any of them reaches 1,000."""
    return "{:,.0f}" if max(abs(v) for v in values) >= 1000 else "{:,.1f}"


def readme_summary(an: Analysis, report_link: str = "docs/reproduction.md") -> list[str]:
    """The claims table in brief: one row per claim and variant, with whether that
    variant's plain learner learns at all (the pilot's test), the arms' means, the
    difference, the Holm-adjusted p and the verdict. Computed from the runs like the
    report, so the README cannot drift from it."""
    if not an.rows:
        return ["No finished runs yet."]
    # Grouped by claim, in the experiments' and their claims' order.
    exp_order = {name: i for i, name in enumerate(EXPERIMENTS)}
    rows = sorted(
        an.rows,
        key=lambda r: (
            exp_order[r.exp_name],
            [c.text for c in EXPERIMENTS[r.exp_name].claims].index(r.claim.text),
        ),
    )
    counts = Counter(row.judge()[0] for row in rows)
    holding = [row for row in rows if row.judge()[0] == "holds"]
    n_done, n_req = an.progress
    lines = [
        (
            f"All {n_req} runs of the grid are finished"
            if n_done == n_req
            else f"{n_done} of the {n_req} runs of the current grid are finished"
        )
        + (f", besides the first report's {len(an.earlier)}" if an.earlier else "")
        + f". The {len(rows)} claim rows ({_distinct_tests(rows)} distinct tests, "
        "Holm-corrected together): "
        + ", ".join(f"{w} {counts[w]}" for w in ("holds", "does not hold", "cannot be decided yet"))
        + "."
        + (
            " Holding: "
            + "; ".join(
                f"{EXPERIMENTS[r.exp_name].short}: {r.claim.text} "
                f"({EXPERIMENTS[r.exp_name].variant(r.variant).label})"
                for r in holding
            )
            + "."
            if holding
            else ""
        )
        + f" Intervals, single terms, plots and how each verdict is reached: [the report]"
        f"({report_link}).",
        "",
        "| claim | variant | plain learns? | ours (mean over seeds) | arm - plain [95% CI] "
        "| Holm p | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    learns: dict[Group, str] = {}
    last_claim = ""
    for row in rows:
        exp = EXPERIMENTS[row.exp_name]
        key = (row.exp_name, row.variant)
        if key not in learns:
            plain = [r for r in an.groups[key] if r.arm == "plain"]
            learns[key] = _plain_learns(row.exp_name, plain).verdict if plain else "-"
        claim = f"{exp.short}: {row.claim.text}"
        arm = ARMS[row.claim.arm].short
        if row.claim.metric == "solved":
            ours = (
                f"{arm} {int(sum(row.arm_values))}/{len(row.arm_values)} solved, plain "
                f"{int(sum(row.plain_values))}/{len(row.plain_values)}"
            )
            diff = "-"
        else:
            a, b = float(np.mean(row.arm_values)), float(np.mean(row.plain_values))
            fmt = _short_fmt(a, b)
            prefix = "≥ " if row.censored and row.claim.metric in CENSORABLE else ""
            ours = f"{prefix}{arm} {fmt.format(a)}, plain {fmt.format(b)}"
            d = row.diff
            diff = (
                "-"
                if math.isnan(d.low)
                else f"{'+' if d.mean > 0 else ''}{fmt.format(d.mean)} "
                f"[{fmt.format(d.low)}, {fmt.format(d.high)}]"
            )
        holm_p = "-" if math.isnan(row.p_holm) else f"{row.p_holm:.2g}"
        lines.append(
            f"| {claim if claim != last_claim else ''} | {exp.variant(row.variant).label} | "
            f"{learns[key]} | {ours} | {diff} | {holm_p} | {row.short_verdict()} |"
        )
        last_claim = claim
    return lines


def update_readme(readme: Path, summary: list[str]) -> bool:
    """Replace the text between :data:`README_BEGIN` and :data:`README_END` in ``readme``
    with ``summary``. Returns whether the file changed; raises ``ValueError`` if the
    markers are missing."""
    text = readme.read_text()
    block = readme_block(text)
    if block is None:
        raise ValueError(f"{readme}: no lines {README_BEGIN!r} ... {README_END!r}")
    new = "\n".join(summary)
    if block == new:
        return False
    head, rest = text.split(README_BEGIN + "\n", 1)
    tail = rest.split("\n" + README_END, 1)[1]
    readme.write_text(head + README_BEGIN + "\n" + new + "\n" + README_END + tail)
    return True


def readme_block(text: str) -> str | None:
    """The README's generated summary as it stands (``None`` without the markers)."""
    if README_BEGIN + "\n" not in text or "\n" + README_END not in text:
        return None
    return text.split(README_BEGIN + "\n", 1)[1].split("\n" + README_END, 1)[0]


def _backend_counts(runs: list[Run]) -> str:
    counts = Counter(r.backend for r in runs)
    words = {
        "engine": "on the embedded engine, in process (`tamrm.Engine()`, one per run)",
        "server": "on a tamrm server over gRPC (including the runs recorded before the "
        "engine existed, whose sidecars name no backend)",
    }
    return "; ".join(
        f"{n} run{'s' if n != 1 else ''} {words.get(b, b)}" for b, n in sorted(counts.items())
    )


def _how_run(runs_dir: Path, runs: list[Run], out: Path, previous: Path | None = None) -> list[str]:
    all_invs = [i for i in _invocations(runs_dir) if i.get("runs_todo")]
    starts = sorted(i["started_utc"] for i in all_invs if "started_utc" in i)
    ends = sorted(i["finished_utc"] for i in all_invs if "finished_utc" in i)
    elapsed = f"between {starts[0]} and {ends[-1]}" if starts and ends else "times unknown"
    run_wall = sum(float(r.meta.get("wall_time_s", 0)) for r in runs)
    total_steps = sum(int(r.meta.get("total_steps", 0)) for r in runs)
    # An invocation whose last record is its start record was still running (or was
    # killed) when this report was written.
    last: dict[str, dict[str, Any]] = {}
    for inv in all_invs:
        last[inv["command"]] = inv
    running = sorted(c for c, inv in last.items() if inv.get("status") == "started")
    commands = sorted(last)
    vers = runs[0].meta.get("versions", {})
    prev = f" --previous {previous}" if previous is not None else ""
    lines = [
        "- The grid invocations (resumable; finished runs are skipped; several may share "
        "the runs directory; * = still running, or ended without its summary, when this "
        "report was written):",
        "",
        *[f"      {c}{' *' if c in running else ''}" for c in commands],
        "",
        f"  then `python -m tamrm_experiments report --runs {runs_dir} --out {out}{prev}`.",
        f"- Wall time of the finished invocations: {_busy_minutes(all_invs):.0f} min with at "
        f"least one running ({elapsed}); sum of the wall times of the {len(runs)} finished runs: "
        f"{run_wall / 60:.1f} min; {total_steps:,} environment steps.",
        "- Backend (where the shaping was computed; the same rewards either way): "
        + _backend_counts(runs)
        + ".",
        "- Versions: " + ", ".join(f"{k} {v}" for k, v in sorted(vers.items())) + ".",
    ]
    varying: dict[str, set[str]] = {}
    for r in runs:
        for k, v in r.meta.get("versions", {}).items():
            varying.setdefault(k, set()).add(str(v))
    parts = [f"{k}: {', '.join(sorted(v))}" for k, v in sorted(varying.items()) if len(v) > 1]
    if parts:
        lines.append(
            "- Versions that differ between runs (the repository moved on while the grid "
            "ran; the server binary or the engine's native extension, and the packages, are "
            "what count): " + "; ".join(parts)
        )
    lines.append("")
    return lines
