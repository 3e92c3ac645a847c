"""The page: ``docs/reproduction.md`` rendered from an :class:`~verdicts.Analysis`.

The claims, the state of the grid (:mod:`tamrm_experiments.grid`), one section per
experiment and variant with its table, its differences to plain, its shaping diagnostics
and its plot (:mod:`tamrm_experiments.plots`), how it was run, and the fixed prose of
``templates/report.md`` (:mod:`tamrm_experiments.template`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from tamrm.trial.stats import fmt_interval, t_interval

from tamrm_experiments import grid
from tamrm_experiments.args import EXPERIMENTS_DIR
from tamrm_experiments.configs import ARMS, EXPERIMENTS, runs_variant
from tamrm_experiments.envs import MAZE_NEW_START, MAZE_START, maze_shortest_path
from tamrm_experiments.load import Run, partials
from tamrm_experiments.plots import plot_experiment
from tamrm_experiments.summary import claims_in_brief, progress
from tamrm_experiments.template import block, block_lines
from tamrm_experiments.verdicts import (
    CENSORABLE,
    Analysis,
    ClaimRow,
    Comparison,
    analyse,
    censoring_caveat,
    compare,
    distinct_tests,
    run_metrics,
)

__all__ = ["render_report", "shown", "write_report"]

#: The repository (paths under it are shown relative to it).
REPO = EXPERIMENTS_DIR.parent


def shown(path: Path) -> str:
    """``path`` as the page names it: relative to the repository if it is in it (so the
    page does not depend on where the report ran), else as given."""
    try:
        return str(path.resolve().relative_to(REPO))
    except ValueError:
        return str(path)


def _maze_values() -> dict[str, object]:
    return {
        "maze_start": MAZE_START,
        "maze_start_path": maze_shortest_path(MAZE_START),
        "maze_new_start": MAZE_NEW_START,
        "maze_new_start_path": maze_shortest_path(MAZE_NEW_START),
    }


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


def experiment_section(
    exp_name: str, runs: list[Run], plots_rel: str, png: Path, variant: str = "clean"
) -> tuple[list[str], str | None]:
    """The section of one experiment and variant, and the title of its plot (to draw at
    ``png``; ``None``: no runs, no plot)."""
    exp = EXPERIMENTS[exp_name]
    title = f"{exp.short}: {exp.variant(variant).label}"
    lines = [f"## {title}", ""]
    if not runs:
        return [*lines, "No finished runs.", ""], None
    metrics: dict[str, list[dict[str, float]]] = {arm: [] for arm in ARMS}
    censored = {arm: 0 for arm in ARMS}
    for r in runs:
        metrics[r.arm].append(run_metrics(r))
        censored[r.arm] += int(bool(r.meta.get("censored")))
    lines.append(f"Budget: {_budget_line(exp_name, runs)}.")
    owner = runs_variant(exp, variant, "plain")
    if owner != variant:
        lines.append(block("shared-plain-sentence", owner=exp.variant(owner).label))
    if len({json.dumps(r.budget, sort_keys=True) for r in runs}) > 1:
        lines += ["", block("mixed-budgets")]
    lines.append("")
    head = ["arm", "seeds", "paper", exp.status_column(), *(m.label for m in exp.metrics)]
    any_censored = any(censored.values())
    if any_censored:
        head.append("episodes done")
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm in ARMS:
        ms = metrics[arm]
        if not ms:
            continue
        row = [ARMS[arm].label, str(len(ms)), exp.paper[arm], exp.status_cell(ms, censored[arm])]
        for m in exp.metrics:
            cell = fmt_interval(t_interval([x[m.key] for x in ms]), m.fmt)
            row.append("≥ " + cell if censored[arm] and m.key in CENSORABLE else cell)
        if any_censored:
            row.append(fmt_interval(t_interval([x["episodes"] for x in ms]), "{:,.1f}"))
        lines.append("| " + " | ".join(row) + " |")
    note = block("cells-note-censored") if any_censored else ""
    lines += ["", f"{block('cells-note')} {note}", ""]
    headline = next(m for m in exp.metrics if m.key == exp.headline)
    plain = [m[headline.key] for m in metrics["plain"]]
    if plain:
        lines += [block("difference-head", metric=headline.label), ""]
        for arm in ARMS:
            if arm == "plain" or not metrics[arm]:
                continue
            comp: Comparison = compare(
                headline, [m[headline.key] for m in metrics[arm]], plain, arm
            )
            if headline.key in CENSORABLE and (censored[arm] or censored["plain"]):
                comp = censoring_caveat(comp, bool(censored[arm]), bool(censored["plain"]))
            lines.append(f"- {ARMS[arm].label}: {comp.text}")
        lines.append("")
    lines += diagnostics(runs)
    lines += [f"![{title}]({plots_rel}/{png.name})", ""]
    return lines, title


def diagnostics(runs: list[Run]) -> list[str]:
    """Per arm: how much each shaping term contributed, per step."""
    lines = [*block_lines("diagnostics-head")]
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


def claims_in_detail(rows: list[ClaimRow]) -> list[str]:
    """The claims table with each row's intervals, test and verdict."""
    from tamrm_experiments.authors_data import authors_summary

    lines = block_lines("claims-detail", tests=distinct_tests(rows))
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


def render_report(
    runs_dir: Path, out: Path, plots_dir: Path, previous: Path | None = None
) -> tuple[str, list[tuple[str, list[Run], Path, str]], Analysis]:
    """The page that :func:`write_report` writes at ``out``, the plots it links
    (experiment, runs, path, title) and the analysis, without writing anything."""
    an = analyse(runs_dir, previous)
    runs, earlier, groups = an.runs, an.earlier, an.groups
    try:
        plots_rel = str(plots_dir.resolve().relative_to(out.parent.resolve()))
    except ValueError:
        plots_rel = str(plots_dir.resolve())
    previous_note = block("previous-note", previous=shown(previous)) if earlier and previous else ""
    lines = [*block_lines("page-head", runs_dir=shown(runs_dir), previous_note=previous_note), ""]
    if not runs:
        return "\n".join([*lines, block("no-runs"), ""]), [], an
    if "quick" in {r.meta["spec"]["profile"] for r in runs}:
        lines += [block("quick-warning"), ""]
    lines += ["## Claims", "", progress(an, page=True), ""]
    brief = claims_in_brief(an)
    if brief:
        lines += [*brief, *block_lines("claims-detail-head"), ""]
    lines += claims_in_detail(an.rows)
    lines += block_lines("status-head")
    lines += grid.status(groups, an.requested, partials(runs_dir))
    lines += grid.shared_plain(groups, runs)
    lines += block_lines("pilot-head", **_maze_values())
    lines += grid.pilot(groups)
    to_plot = []
    for (exp_name, variant), rs in groups.items():
        png = plots_dir / f"{exp_name}-{variant}.png"
        section, title = experiment_section(exp_name, rs, plots_rel, png, variant)
        lines += section
        if title is not None:
            to_plot.append((exp_name, rs, png, title))
    shown_previous = shown(previous) if earlier and previous is not None else None
    lines += grid.how_run(an, shown(runs_dir), shown(out), shown_previous)
    lines += grid.cost(groups, an.requested)
    lines += block_lines("deviations", **_maze_values())
    lines += ["", *block_lines("reading"), ""]
    return "\n".join(lines), to_plot, an


def write_report(
    runs_dir: Path, out: Path, plots_dir: Path, previous: Path | None = None
) -> Analysis:
    """Write the markdown page ``out`` and the plots into ``plots_dir``; return what it
    was computed from.

    ``previous``: a runs directory of the first report (runs without a variant), shown as
    the ``clean-v1`` variant: complete as it stands (nothing pending)."""
    text, to_plot, an = render_report(runs_dir, out, plots_dir, previous)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    for exp_name, rs, png, title in to_plot:
        plot_experiment(exp_name, rs, png, title)
    return an
