"""The study's results page (docs/regimes.md) and plots, from the run records alone.

The tests are the plan's (docs/regimes/plan.md): per variant, each arm against plain on
the AUC of the unshaped return, paired by seed, Wilcoxon signed-rank, Holm over all these
primary tests, and the equivalence test (two one-sided signed-rank tests within ±10 % of
plain's mean AUC) before "no effect"; tamrm against sil; the mechanism as a
difference in differences (deterministic - sticky, fixed - procedural) per seed; timesteps
to the first success and to 90 % success, censored at the budget.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tamrm.trial.analysis import curve, run_metrics
from tamrm.trial.stats import (
    Interval,
    bootstrap_interval,
    fmt,
    fmt_interval,
    holm,
    seeds_needed,
    t_interval,
    wilcoxon_equivalence_p,
    wilcoxon_p,
)

from tamrm_regimes.runs import read_record
from tamrm_regimes.study import (
    BUDGET,
    FAMILY_ARMS,
    PILOT_BUDGET,
    PILOT_VARIANTS,
    VARIANTS,
    Scale,
    config_id,
    family_variants,
    sil_grid,
    stage_a_grid,
    stage_b_grid,
)

__all__ = ["load", "write_report"]

LEVEL = 0.05
MARGIN = 0.10
#: Episodes of the rolling success rate that must reach 90 %.
SUCCESS_WINDOW = 20
#: The mechanism's contrasts: (family, variant where it should work, its control, arms).
CONTRASTS = (
    ("E1", "E1-det", "E1-sticky", ("tamrm", "knn", "oracle")),
    ("E2", "E2-fixed", "E2-proc", ("tamrm", "knn")),
)


@dataclass(frozen=True)
class Metrics:
    """One run's numbers."""

    auc: float
    final: float
    first_success: float
    first_success_censored: bool
    success90: float
    success90_censored: bool
    #: CPU seconds (wall seconds in records without them).
    cpu: float


def metrics(record: Mapping[str, Any]) -> Metrics:
    """A run's AUC, final return and success times (censored at its budget)."""
    budget = int(record["study"]["timesteps"])
    m = run_metrics(record, budget, None)
    ends = record["episodes"]["timestep"]
    success = [bool(s) for s in record["episodes"].get("success", [])]
    first = next((e for e, s in zip(ends, success, strict=True) if s), None)
    ninety = None
    for i in range(SUCCESS_WINDOW - 1, len(success)):
        if sum(success[i - SUCCESS_WINDOW + 1 : i + 1]) >= 0.9 * SUCCESS_WINDOW:
            ninety = ends[i]
            break
    return Metrics(
        m.auc,
        m.final,
        float(first if first is not None else budget),
        first is None,
        float(ninety if ninety is not None else budget),
        ninety is None,
        float(record.get("cpu_time_s", record["wall_time_s"])),
    )


def load(runs: Path, stage: str) -> dict[tuple[str, str, int], tuple[Metrics, Mapping[str, Any]]]:
    """Every record of a stage: (variant, arm folder, seed) -> (metrics, record)."""
    out: dict[tuple[str, str, int], tuple[Metrics, Mapping[str, Any]]] = {}
    for path in sorted((runs / stage).glob("*/*/seed*.json.gz")):
        record = read_record(path)
        if record is None:
            continue
        seed = int(path.name.removeprefix("seed").removesuffix(".json.gz"))
        out[(path.parent.parent.name, path.parent.name, seed)] = (metrics(record), record)
    return out


@dataclass
class Row:
    """One comparison of paired runs."""

    label: str
    diffs: list[float]
    plain_mean: float
    p: float = math.nan
    p_holm: float = math.nan
    eq_p: float = math.nan
    interval: Interval | None = None

    def finish(self) -> None:
        self.interval = bootstrap_interval(self.diffs)
        self.p = wilcoxon_p(self.diffs)
        self.eq_p = wilcoxon_equivalence_p(self.diffs, MARGIN * abs(self.plain_mean))

    @property
    def verdict(self) -> str:
        assert self.interval is not None
        if len(self.diffs) >= 2 and self.p_holm < LEVEL and self.interval.mean != 0:
            return "helps" if self.interval.mean > 0 else "hurts"
        if len(self.diffs) >= 2 and self.eq_p < LEVEL:
            return "no effect (equivalent within ±10 %)"
        needed = seeds_needed(self.diffs, MARGIN * abs(self.plain_mean))
        more = f"; ~{needed} seeds would tell" if needed else ""
        return f"inconclusive{more}"


def _folder(arm: str, frozen: Mapping[str, Any], family: str) -> str:
    if arm in ("knn", "tamrm", "oracle"):
        return f"{arm}-{frozen[family]['shaping_id']}"
    if arm == "sil":
        return f"sil-{frozen[family]['sil_id']}"
    return arm


def _paired(
    data: Mapping[tuple[str, str, int], tuple[Metrics, Any]],
    variant: str,
    a: str,
    b: str,
    attr: str,
) -> dict[int, float]:
    """Per seed with both: metric of folder ``a`` minus metric of folder ``b``."""
    out = {}
    for (v, folder, seed), (m, _) in data.items():
        if v == variant and folder == a and (variant, b, seed) in data:
            out[seed] = getattr(m, attr) - getattr(data[(variant, b, seed)][0], attr)
    return out


def _plot(
    variant: str, data: Mapping[tuple[str, str, int], tuple[Metrics, Any]], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.8), dpi=100)
    folders = sorted({f for (v, f, _) in data if v == variant})
    for folder in folders:
        records = [r for (v, f, _), (_, r) in data.items() if v == variant and f == folder]
        budget = int(records[0]["study"]["timesteps"])
        ys = np.vstack([curve(r, budget) for r in records])
        xs = np.linspace(0, budget, ys.shape[1] + 1)[1:]
        mean = ys.mean(axis=0)
        arm = folder.split("-")[0]
        ax.plot(xs, mean, label=f"{arm} (n={len(records)})", lw=1.4)
        if len(records) > 1:
            band = [t_interval(ys[:, i].tolist()) for i in range(ys.shape[1])]
            ax.fill_between(xs, [b.low for b in band], [b.high for b in band], alpha=0.12, lw=0)
    ax.set_title(f"{variant}: unshaped return, mean and 95 % band over seeds")
    ax.set_xlabel("timesteps")
    ax.set_ylabel("episodic return")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _tuning_lines(runs: Path, frozen: Mapping[str, Any], scale: Scale) -> list[str]:
    tune = load(runs, "tune")
    out = ["## Tuning", ""]
    for family in BUDGET:
        variant = family_variants(family)[0].name
        if family not in frozen:
            continue
        out += [
            f"### {family} (tuned on {variant}, seeds {', '.join(map(str, scale.tune_seeds))})",
            "",
        ]
        plain = [m.auc for (v, f, _), (m, _) in tune.items() if v == variant and f == "plain"]
        out.append(f"plain: AUC {fmt_interval(t_interval(plain), '{:.3f}')}.")
        out += ["", "| arm | setting | AUC (mean over tuning seeds) |", "|---|---|---|"]
        best_a = frozen[family]["shaping"]
        grids = [("tamrm", c) for c in scale.cut(stage_a_grid()) + scale.cut(stage_b_grid(best_a))]
        grids += [("sil", c) for c in scale.cut(sil_grid())]
        seen = set()
        for arm, config in grids:
            folder = f"{arm}-{config_id(config)}"
            if folder in seen:
                continue
            seen.add(folder)
            values = [m.auc for (v, f, _), (m, _) in tune.items() if v == variant and f == folder]
            chosen = folder in (
                f"tamrm-{frozen[family]['shaping_id']}",
                f"sil-{frozen[family]['sil_id']}",
            )
            text = ", ".join(f"{k}={val}" for k, val in sorted(config.items()))
            mean = fmt(float(np.mean(values)) if values else math.nan, "{:.3f}")
            out.append(
                f"| {arm} | {'**' + text + '**' if chosen else text} | {mean} ({len(values)}) |"
            )
        out.append("")
    return out


def write_report(runs: Path, out: Path, scale: Scale) -> None:
    """Write the results page and its plots from the records under ``runs``."""
    frozen_path = runs / "frozen.json"
    frozen: dict[str, Any] = json.loads(frozen_path.read_text()) if frozen_path.is_file() else {}
    confirm = load(runs, "confirm")
    plots = out.parent / "regimes"
    plots.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Where shaping helps: the regime study",
        "",
        "<!-- generated by `python -m tamrm_regimes report` from the run records; do not edit -->",
        "",
        "The plan, committed before the confirmatory runs: [regimes/plan.md](regimes/plan.md).",
        "Every number is the environment's own (unshaped) episodic return, Stable-Baselines3 PPO,",
        "paired seeds. AUC: the mean return over training (area under the curve / budget).",
        "",
    ]
    primary: list[Row] = []
    tables: dict[str, list[Row]] = {}
    for family, arms in FAMILY_ARMS.items():
        if family not in frozen:
            continue
        for variant in family_variants(family):
            rows = []
            plain_auc = [
                m.auc for (v, f, _), (m, _) in confirm.items() if v == variant.name and f == "plain"
            ]
            for arm in arms:
                if arm == "plain":
                    continue
                diffs = _paired(confirm, variant.name, _folder(arm, frozen, family), "plain", "auc")
                row = Row(
                    f"{variant.name} {arm}",
                    list(diffs.values()),
                    float(np.mean(plain_auc)) if plain_auc else math.nan,
                )
                row.finish()
                rows.append(row)
                primary.append(row)
            tables[variant.name] = rows
    for row, p in zip(primary, holm([r.p for r in primary]), strict=True):
        row.p_holm = p
    lines += [
        "## The regime table",
        "",
        f"Each arm against plain on the AUC: mean paired difference with a bootstrap 95 % "
        f"interval, Wilcoxon p Holm-adjusted over all {len(primary)} primary tests, the "
        "equivalence test's p (±10 % of plain's AUC), the verdict.",
        "",
        "| variant | arm | seeds | AUC difference, 95 % CI | relative | p (Holm) "
        "| equivalence p | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in tables.items():
        for row in rows:
            assert row.interval is not None
            rel = row.interval.mean / abs(row.plain_mean) if row.plain_mean else math.nan
            lines.append(
                f"| {name} | {row.label.split()[1]} | {len(row.diffs)} "
                f"| {fmt_interval(row.interval, '{:+.3f}')} | {fmt(rel * 100, '{:+.0f} %')} "
                f"| {fmt(row.p_holm, '{:.3g}')} | {fmt(row.eq_p, '{:.3g}')} | {row.verdict} |"
            )
    lines.append("")
    for name in tables:
        _plot(name, {k: v for k, v in confirm.items() if k[0] == name}, plots / f"{name}.png")
        lines.append(f"![{name}](regimes/{name}.png)")
    lines.append("")
    lines += _against_sil(confirm, frozen)
    lines += _mechanism(confirm, frozen)
    lines += _success(confirm, frozen)
    lines += _tuning_lines(runs, frozen, scale)
    lines += _budget(runs)
    out.write_text("\n".join(lines).rstrip() + "\n")


def _against_sil(confirm: Any, frozen: Mapping[str, Any]) -> list[str]:
    rows = []
    for family in frozen:
        for variant in family_variants(family):
            diffs = _paired(
                confirm,
                variant.name,
                _folder("tamrm", frozen, family),
                _folder("sil", frozen, family),
                "auc",
            )
            plain = [
                m.auc for (v, f, _), (m, _) in confirm.items() if v == variant.name and f == "plain"
            ]
            row = Row(
                variant.name, list(diffs.values()), float(np.mean(plain)) if plain else math.nan
            )
            row.finish()
            rows.append(row)
    for row, p in zip(rows, holm([r.p for r in rows]), strict=True):
        row.p_holm = p
    out = [
        "## TAMRM against self-imitation learning",
        "",
        "tamrm - sil on the AUC, paired by seed, Holm over the variants.",
        "",
        "| variant | seeds | difference, 95 % CI | p (Holm) | verdict |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        assert row.interval is not None
        out.append(
            f"| {row.label} | {len(row.diffs)} | {fmt_interval(row.interval, '{:+.3f}')} "
            f"| {fmt(row.p_holm, '{:.3g}')} | {row.verdict} |"
        )
    return [*out, ""]


def _mechanism(confirm: Any, frozen: Mapping[str, Any]) -> list[str]:
    rows = []
    for family, works, control, arms in CONTRASTS:
        if family not in frozen:
            continue
        for arm in arms:
            folder = _folder(arm, frozen, family)
            a = _paired(confirm, works, folder, "plain", "auc")
            b = _paired(confirm, control, folder, "plain", "auc")
            seeds = sorted(set(a) & set(b))
            plain = [m.auc for (v, f, _), (m, _) in confirm.items() if v == works and f == "plain"]
            row = Row(
                f"{arm}: {works} - {control}",
                [a[s] - b[s] for s in seeds],
                float(np.mean(plain)) if plain else math.nan,
            )
            row.finish()
            rows.append(row)
    for row, p in zip(rows, holm([r.p for r in rows]), strict=True):
        row.p_holm = p
    out = [
        "## The mechanism: difference in differences",
        "",
        "Per seed, (arm - plain) where an action prefix names a state minus (arm - plain) "
        "where it does not; a positive difference says the arm's effect needs the "
        "mechanism TAMRM relies on. Holm over these tests.",
        "",
        "| contrast | seeds | difference, 95 % CI | p (Holm) |",
        "|---|---|---|---|",
    ]
    for row in rows:
        assert row.interval is not None
        out.append(
            f"| {row.label} | {len(row.diffs)} | {fmt_interval(row.interval, '{:+.3f}')} "
            f"| {fmt(row.p_holm, '{:.3g}')} |"
        )
    return [*out, ""]


def _success(confirm: Any, frozen: Mapping[str, Any]) -> list[str]:
    out = [
        "## Timesteps to the first success and to 90 % success",
        "",
        f"Means over seeds with t-intervals; 90 %: the rolling success rate of {SUCCESS_WINDOW} "
        "episodes. A run that never gets there counts at its budget (censored: the count in "
        "brackets), so a mean with censored runs is a lower bound.",
        "",
        "| variant | arm | first success | 90 % success |",
        "|---|---|---|---|",
    ]
    for family, arms in FAMILY_ARMS.items():
        if family not in frozen:
            continue
        for variant in family_variants(family):
            for arm in arms:
                folder = _folder(arm, frozen, family)
                ms = [
                    m for (v, f, _), (m, _) in confirm.items() if v == variant.name and f == folder
                ]
                if not ms:
                    continue
                first = fmt_interval(t_interval([m.first_success for m in ms]), "{:,.0f}")
                ninety = fmt_interval(t_interval([m.success90 for m in ms]), "{:,.0f}")
                out.append(
                    f"| {variant.name} | {arm} "
                    f"| {first} ({sum(m.first_success_censored for m in ms)}) "
                    f"| {ninety} ({sum(m.success90_censored for m in ms)}) |"
                )
    return [*out, ""]


def _budget(runs: Path) -> list[str]:
    out = ["## Budget spent", "", "| stage | runs | CPU-hours |", "|---|---|---|"]
    total = 0.0
    for stage in ("pilot", "tune", "confirm"):
        data = load(runs, stage)
        hours = sum(m.cpu for m, _ in data.values()) / 3600
        total += hours
        out.append(f"| {stage} | {len(data)} | {hours:.1f} |")
    out.append(f"| all | | {total:.1f} |")
    return [*out, ""]


def pilot_table(runs: Path) -> list[str]:
    """The pilot's plain runs: per variant, the final return and each seed's timesteps to
    90 % success ("never" within the budget)."""
    data = load(runs, "pilot")
    out = [
        "| variant | budget | seeds | final return | timesteps to 90 % success, per seed |",
        "|---|---|---|---|---|",
    ]
    for name, variant in PILOT_VARIANTS.items():
        ms = [m for (v, _, _), (m, _) in sorted(data.items()) if v == name]
        if not ms:
            continue
        times = ", ".join("never" if m.success90_censored else f"{m.success90:,.0f}" for m in ms)
        out.append(
            f"| {name} | {PILOT_BUDGET[variant.family]:,} | {len(ms)} "
            f"| {fmt_interval(t_interval([m.final for m in ms]), '{:.3f}')} | {times} |"
        )
    return out


assert set(VARIANTS) >= {w for _, w, _, _ in CONTRASTS}
