"""A trial's report: ``report.md`` (read in a minute), ``curves.png``, ``summary.json``.

Made from the run records alone, so it can be made again at any time (``--report-only``),
and from a trial that was interrupted: it says which runs are missing or failed.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from tamrm.trial.analysis import (
    CURVE_POINTS,
    LEVEL,
    Comparison,
    RunMetrics,
    compare,
    curve,
    null_identity,
    run_metrics,
)
from tamrm.trial.runner import load_records
from tamrm.trial.settings import ARMS, TrialSettings, run_name
from tamrm.trial.stats import fmt, fmt_interval, min_signed_rank_p, t_interval

__all__ = ["Report", "write_report"]

_METRIC_NAMES = {
    "auc": "AUC (mean return over training)",
    "final": "final return (last 10 % of timesteps)",
    "to_threshold": "timesteps to the threshold",
}
_COLOURS = {
    "plain": "#444444",
    "null": "#999999",
    "knn": "#1f77b4",
    "pbrs": "#2ca02c",
    "tamrm": "#d62728",
}


class Report:
    """The analysis of a trial's records, ready to be written."""

    def __init__(self, settings: TrialSettings, out: Path) -> None:
        self.settings = settings
        self.out = out
        self.records, self.failures = load_records(out, settings)
        self.metrics: dict[tuple[str, int], RunMetrics] = {
            run: run_metrics(record, settings.timesteps, settings.threshold)
            for run, record in self.records.items()
        }
        self.comparisons: list[Comparison] = (
            compare(self.metrics, settings.arms, settings.margin, settings.threshold)
            if "plain" in settings.arms
            else []
        )
        self.null = null_identity(self.records)
        self.missing = [
            run for run in settings.runs() if run not in self.records and run not in self.failures
        ]

    def arm_interval(self, arm: str, metric: str) -> Any:
        """The t-interval over seeds of one arm's metric."""
        values = [getattr(m, metric) for (a, _), m in self.metrics.items() if a == arm]
        return t_interval([math.nan if v is None else float(v) for v in values])

    # -- summary.json ------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """The machine-readable summary."""
        s = self.settings
        return {
            "settings": s.to_json(),
            "runs": {
                "expected": len(s.runs()),
                "finished": len(self.records),
                "failed": {run_name(*run): err for run, err in self.failures.items()},
                "missing": [run_name(*run) for run in self.missing],
            },
            "arms": {
                arm: {
                    metric: _interval_json(self.arm_interval(arm, metric))
                    for metric in ("auc", "final", "episodes")
                    + (("to_threshold",) if s.threshold is not None else ())
                }
                for arm in s.arms
            },
            "comparisons": [c.to_json() for c in self.comparisons],
            "null_identical_to_plain": {
                str(seed): same for seed, same in sorted(self.null.items())
            },
        }

    # -- curves.png --------------------------------------------------------------------

    def plot(self, path: Path) -> None:
        """Unshaped return against timesteps: mean and 95 % band over seeds, per arm."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        s = self.settings
        xs = np.linspace(0, s.timesteps, CURVE_POINTS + 1)[1:]
        fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=110)
        for arm in s.arms:
            curves = [curve(r, s.timesteps) for (a, _), r in self.records.items() if a == arm]
            if not curves:
                continue
            ys = np.vstack(curves)
            band = [t_interval(ys[:, i].tolist()) for i in range(ys.shape[1])]
            mean = np.array([b.mean for b in band])
            colour = _COLOURS.get(arm)
            style = "--" if arm == "null" else "-"
            ax.plot(xs, mean, style, color=colour, label=f"{arm} (n={len(curves)})", lw=1.6)
            if len(curves) > 1:
                low = np.array([b.low for b in band])
                high = np.array([b.high for b in band])
                ax.fill_between(xs, low, high, color=colour, alpha=0.15, lw=0)
        if s.threshold is not None:
            ax.axhline(s.threshold, color="#888888", lw=0.8, ls=":", label="threshold")
        ax.set_xlabel("timesteps")
        ax.set_ylabel("episodic return (the environment's, unshaped)")
        ax.set_title(f"{s.env}, {s.algo.upper()}: mean and 95 % band over seeds")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)

    # -- report.md ---------------------------------------------------------------------

    def markdown(self) -> str:
        """The report a person reads in a minute."""
        s = self.settings
        lines = [
            f"# Does shaping help? {s.env}, {s.algo.upper()}, {s.timesteps:,} timesteps, "
            f"{s.seeds} paired seed{'s' * (s.seeds != 1)}",
            "",
        ]
        lines += self._verdict_lines()
        lines += ["", "![learning curves](curves.png)", ""]
        lines += self._arms_table()
        if self.comparisons:
            lines += self._comparison_table()
        lines += self._harness_lines()
        lines += self._runs_lines()
        lines += self._settings_lines()
        lines += _READING
        return "\n".join(lines).rstrip() + "\n"

    def _verdict_lines(self) -> list[str]:
        s = self.settings
        if not s.verdict:
            return ["No verdict was asked for (`--no-verdict`): curves and metrics only."]
        if "plain" not in s.arms:
            return ["No verdict: the trial has no `plain` arm to compare with."]
        out = [
            "**Verdict** (each arm against plain, on the area under the unshaped return curve):",
            "",
        ]
        for c in self.comparisons:
            out.append(f"- **{c.headline}** {c.sentence}")
        if not self.comparisons:
            out.append("- no arm to compare with plain")
        n = min((c.tests["auc"].n for c in self.comparisons), default=0)
        if self.comparisons and min_signed_rank_p(n) >= LEVEL:
            out += [
                "",
                f"With {n} paired seeds the signed-rank test cannot reach p < {LEVEL:g} "
                "whatever the runs do: run at least 6 (more with several arms) for a verdict.",
            ]
        if self.missing or self.failures:
            out += [
                "",
                f"**Incomplete**: {len(self.records)} of {len(s.runs())} runs finished "
                f"({len(self.failures)} failed, {len(self.missing)} not run); the verdict uses "
                "the finished pairs only. `--resume` runs the rest.",
            ]
        return out

    def _arms_table(self) -> list[str]:
        s = self.settings
        head = "| arm | runs | AUC, 95 % CI | final return | episodes |"
        rule = "|---|---|---|---|---|"
        if s.threshold is not None:
            head += f" timesteps to {s.threshold:g} (censored) |"
            rule += "---|"
        out = ["## Each arm", "", "Means over seeds with t-based 95 % intervals.", "", head, rule]
        for arm in s.arms:
            runs = [m for (a, _), m in self.metrics.items() if a == arm]
            row = (
                f"| {arm} | {len(runs)} | {fmt_interval(self.arm_interval(arm, 'auc'), '{:.4g}')} "
                f"| {fmt_interval(self.arm_interval(arm, 'final'), '{:.4g}')} "
                f"| {fmt(self.arm_interval(arm, 'episodes').mean, '{:.0f}')} |"
            )
            if s.threshold is not None:
                censored = sum(m.censored for m in runs)
                reach = fmt_interval(self.arm_interval(arm, "to_threshold"), "{:,.0f}")
                row += f" {reach} ({censored}) |"
            out.append(row)
        return [*out, ""]

    def _comparison_table(self) -> list[str]:
        out = [
            "## Against plain, paired by seed",
            "",
            "Mean of the per-seed differences (arm - plain) with a bootstrap 95 % interval; "
            "Wilcoxon signed-rank p, then Holm-adjusted over the arms.",
            "",
            "| arm | metric | pairs | difference, 95 % CI | p | p (Holm) |",
            "|---|---|---|---|---|---|",
        ]
        for c in self.comparisons:
            for metric, t in c.tests.items():
                better = " (lower is better)" if t.better == "lower" else ""
                out.append(
                    f"| {c.arm} | {_METRIC_NAMES[metric]}{better} | {t.n} "
                    f"| {fmt_interval(t.difference, '{:+.4g}')} | {fmt(t.p, '{:.3g}')} "
                    f"| {fmt(t.p_holm, '{:.3g}')} |"
                )
        margin = self.comparisons[0].margin
        out += ["", f"Equivalence margin: ±{fmt(margin, '{:.4g}')} ({self.settings.margin})."]
        if self.settings.threshold is not None:
            out += [
                "Runs that never reach the threshold count as reaching it at the budget "
                "(censored): their differences are bounds, not values.",
            ]
        return [*out, ""]

    def _harness_lines(self) -> list[str]:
        if not self.null:
            return []
        same = sum(self.null.values())
        verdict = "identical" if same == len(self.null) else "NOT identical"
        return [
            "## The harness check",
            "",
            "The `null` arm (alpha = beta = 0 through the shaping path) learned "
            f"{verdict} to `plain` in {same} of {len(self.null)} seeds (episodes, returns and "
            "final parameters, bit for bit).",
            "",
        ]

    def _runs_lines(self) -> list[str]:
        out: list[str] = []
        if self.failures:
            out += ["## Failed runs", ""]
            out += [f"- `{run_name(*run)}`: {err}" for run, err in sorted(self.failures.items())]
            out.append("")
        cpu = [r.get("cpu_time_s", r["wall_time_s"]) for r in self.records.values()]
        if cpu:
            out += [
                "## Cost",
                "",
                f"{len(cpu)} runs, {sum(cpu) / 3600:.2f} CPU-hours in all "
                f"(median {float(np.median(cpu)):.0f} CPU-seconds a run).",
                "",
            ]
        return out

    def _settings_lines(self) -> list[str]:
        s = self.settings
        task = ", ".join(f"{k} = {v}" for k, v in sorted(s.task.items())) or "SPEC's defaults"
        hyper = (
            f"from `{s.hyperparams_file}`: {json.dumps(dict(s.hyperparams), sort_keys=True)}"
            if s.hyperparams
            else "Stable-Baselines3's defaults"
        )
        backend = f"a server at {s.server} (local sessions)" if s.server else "the embedded engine"
        return [
            "## Settings",
            "",
            f"- Environment `{s.env}`"
            + (f" with {json.dumps(dict(s.env_kwargs))}" if s.env_kwargs else "")
            + (f", registered by {', '.join(s.env_modules)}" if s.env_modules else ""),
            f"- {s.algo.upper()}, hyperparameters {hyper}",
            f"- Seeds {s.seed0}..{s.seed0 + s.seeds - 1}, each arm's seed s with the same env "
            "and model seed",
            f"- Shaping: {task}; arms {', '.join(s.arms)}; on {backend}",
            "",
        ]

    def write(self) -> dict[str, Any]:
        """Write ``report.md``, ``curves.png`` and ``summary.json``; return the summary."""
        summary = self.summary()
        self.plot(self.out / "curves.png")
        (self.out / "report.md").write_text(self.markdown())
        (self.out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
        return summary


def _interval_json(iv: Any) -> dict[str, float | int | None]:
    def clean(x: float) -> float | None:
        return None if math.isnan(x) else x

    return {"mean": clean(iv.mean), "low": clean(iv.low), "high": clean(iv.high), "n": iv.n}


_READING = [
    "## How to read this",
    "",
    "- Every number is the environment's own episodic return, recorded below the shaping "
    "wrapper: shaped rewards are never compared (they differ by construction).",
    "- AUC is the area under the return curve divided by the budget: it rewards learning "
    "sooner as well as learning more. The final return says where runs ended up.",
    "- Seeds are paired: seed s of every arm starts from the same environment and network; "
    "the tests are on the per-seed differences.",
    "- *Not enough seeds to tell* is not *no effect*: only the equivalence test can say that.",
]


def write_report(settings: TrialSettings, out: Path) -> Mapping[str, Any]:
    """Analyse the trial's records under ``out`` and write its report files."""
    return Report(settings, out).write()


assert set(_COLOURS) == set(ARMS)
