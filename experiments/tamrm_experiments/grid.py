"""The state of the grid, rendered: which runs are done and pending, the shared plain arms,
the pilot of the plain learners, how the runs were made and what the pending ones cost."""

from __future__ import annotations

import datetime as dt
import math
from collections import Counter
from typing import Any

from tamrm.trial.stats import fmt_interval, t_interval

from tamrm_experiments.configs import ARMS, EXPERIMENTS, runs_variant
from tamrm_experiments.load import Group, Key, Run, invocations, wanted
from tamrm_experiments.template import block, block_lines
from tamrm_experiments.verdicts import Analysis, plain_learns

__all__ = ["busy_minutes", "cost", "how_run", "pilot", "seed_list", "shared_plain", "status"]


#: Columns of a run's CSV that a rerun with the same seed reproduces (not the wall time,
#: nor the shaping diagnostics, which depend on the variant's pool settings).
REPLAYED = ("episode", "steps", "env_return", "terminated", "truncated", "success", "score")


def shared_plain(groups: dict[Group, list[Run]], runs: list[Run]) -> list[str]:
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
                f" Earlier plain runs of its own (seeds {seed_list(sorted(r.seed for r in own))}"
                f"), kept in the raw data: {len(same)} identical episode by episode to the shared "
                f"run of the same seed, {len(differ)} different"
                + (f" (seeds {seed_list(differ)})" if differ else "")
                + ", "
                + f"{len(own) - len(same) - len(differ)} without a shared run to compare."
            )
        lines.append(text)
    if not lines:
        return []
    return [block("shared-plain-head"), "", *lines, ""]


def _replays(a: Run, b: Run) -> bool:
    """Whether two runs have the same episodes (``REPLAYED`` columns)."""
    cols = [c for c in REPLAYED if c in a.df.columns and c in b.df.columns]
    return len(a.df) == len(b.df) and a.df[cols].reset_index(drop=True).equals(
        b.df[cols].reset_index(drop=True)
    )


# -- status, pilot, cost ---------------------------------------------------------------


def status(
    groups: dict[Group, list[Run]], requested: list[Key], partial: dict[Key, int]
) -> list[str]:
    """The rows of the status table: per group and arm, the seeds done and pending (with
    the episodes so far of a run in progress, from ``partial``)."""
    lines = []
    for (exp_name, variant), runs in groups.items():
        exp = EXPERIMENTS[exp_name]
        for arm in ARMS:
            done = sorted(r.seed for r in runs if r.arm == arm)
            want = wanted(requested, exp_name, variant, arm)
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
                f"{len(done)}: {seed_list(done)} | {len(pending)}"
                + (f": {', '.join(pend)}" if pend else "")
                + " |"
            )
    lines.append("")
    return lines


def seed_list(seeds: list[int]) -> str:
    if not seeds:
        return "-"
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def pilot(groups: dict[Group, list[Run]]) -> list[str]:
    """The rows of the pilot's table: does each variant's plain learner learn within the
    budget? First vs last episodes, and the last episodes vs a uniformly random policy."""
    lines = []
    for (exp_name, variant), runs in groups.items():
        plain = [r for r in runs if r.arm == "plain" and len(r.df) >= 40]
        if not plain or any(r.variant != variant for r in plain):
            continue  # none, or another variant's plain runs (listed under that variant)
        exp = EXPERIMENTS[exp_name]
        pilot = plain_learns(exp_name, plain)
        lines.append(
            f"| {exp.short} | {exp.variant(variant).label} | {len(plain)} | "
            f"{fmt_interval(pilot.first, '{:,.1f}')} | {fmt_interval(pilot.last, '{:,.1f}')} "
            f"| {pilot.random_policy:,.1f} | {pilot.verdict} |"
        )
    lines.append("")
    return lines


def _backends(runs: list[Run]) -> str:
    """The runs' backends, counted: ``server``, or ``engine 3, server 10`` when mixed."""
    counts = Counter(r.backend for r in runs)
    if len(counts) == 1:
        return next(iter(counts))
    return ", ".join(f"{b} {n}" for b, n in sorted(counts.items()))


def cost(groups: dict[Group, list[Run]], requested: list[Key]) -> list[str]:
    """The cost table: per group, the measured cost per run and the pending runs'."""
    lines = block_lines("cost-head")
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
            f"{_backends(runs) if runs else '-'} | {fmt_interval(steps, '{:,.0f}')} | "
            + (f"{fmt_interval(wall, '{:,.1f}')} min" if runs else "-")
            + f" | {fmt_interval(rate, '{:,.0f}')} | {len(pending)} | {est} |"
        )
    lines += ["", block("cost-foot", hours=f"{total_pending:,.1f}"), ""]
    return lines


def busy_minutes(invocations: list[dict[str, Any]]) -> float:
    """Minutes in the union of the invocations' [start, finish] intervals: wall time
    during which the grid was running, not counting the gaps between sessions."""
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


def _backend_counts(runs: list[Run]) -> str:
    counts = Counter(r.backend for r in runs)
    words = {b: block(f"backend-{b}") for b in ("engine", "server")}
    return "; ".join(
        f"{n} run{'s' if n != 1 else ''} {words.get(b, b)}" for b, n in sorted(counts.items())
    )


def how_run(an: Analysis, runs_dir: str, out: str, previous: str | None) -> list[str]:
    """How the runs were made: the invocations, the report's command (``runs_dir``,
    ``out`` and ``previous`` as the page names them), the time, the backends and the
    versions."""
    runs = an.current or an.runs
    all_invs = [i for i in invocations(an.runs_dir) if i.get("runs_todo")]
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
    vers = runs[0].meta.get("versions", {})
    lines = [
        *block_lines("how-run-invocations"),
        "",
        *[f"      {c}{' *' if c in running else ''}" for c in sorted(last)],
        "",
        *block_lines(
            "how-run",
            runs_dir=runs_dir,
            out=out,
            previous=f" --previous {previous}" if previous is not None else "",
            busy=f"{busy_minutes(all_invs):.0f}",
            elapsed=elapsed,
            n_runs=len(runs),
            run_minutes=f"{run_wall / 60:.1f}",
            steps=f"{total_steps:,}",
            backends=_backend_counts(runs),
            versions=", ".join(f"{k} {v}" for k, v in sorted(vers.items())),
        ),
    ]
    varying: dict[str, set[str]] = {}
    for r in runs:
        for k, v in r.meta.get("versions", {}).items():
            varying.setdefault(k, set()).add(str(v))
    parts = [f"{k}: {', '.join(sorted(v))}" for k, v in sorted(varying.items()) if len(v) > 1]
    if parts:
        lines.append(block("versions-differ", parts="; ".join(parts)))
    lines.append("")
    return lines
