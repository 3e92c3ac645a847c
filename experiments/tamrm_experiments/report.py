"""Turn the raw runs into ``docs/reproduction.md``, its plots and the README's summary.

Everything in the page is computed from the runs directory: the tables, the verdicts and
the closing note. Nothing is typed in by hand except the paper's own figures and the prose
of ``templates/report.md`` (which describes the setup, not the results). The work is split
by job: :mod:`~tamrm_experiments.load` (runs to frames), :mod:`~tamrm_experiments.verdicts`
(metrics, claims, statistics), :mod:`~tamrm_experiments.plots`,
:mod:`~tamrm_experiments.markdown` and :mod:`~tamrm_experiments.grid` (the page) and
:mod:`~tamrm_experiments.summary` (the claims in brief, the README's summary); this module
gathers their public names.
"""

from __future__ import annotations

from tamrm_experiments.load import Run, load_runs
from tamrm_experiments.markdown import write_report
from tamrm_experiments.summary import (
    README_BEGIN,
    README_END,
    readme_block,
    readme_summary,
    update_readme,
)
from tamrm_experiments.verdicts import Analysis, analyse, run_metrics

__all__ = [
    "README_BEGIN",
    "README_END",
    "Analysis",
    "Run",
    "analyse",
    "load_runs",
    "readme_block",
    "readme_summary",
    "run_metrics",
    "update_readme",
    "write_report",
]
