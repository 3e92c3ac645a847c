"""Does shaping help on my task? An honest A/B of tamrm's shaping (``tamrm-trial``).

Install with ``pip install 'tamrm[trial]'``, then::

    tamrm-trial --env CartPole-v1 --algo a2c --timesteps 50000 --seeds 10 --out cartpole-trial

Each arm (``plain``: no shaping; ``tamrm``; ``knn``, ``pbrs`` and ``null`` on request)
trains the same Stable-Baselines3 learner on the same paired seeds; every arm is scored on
the environment's own return. The report (``report.md``, ``curves.png``,
``summary.json``) compares each arm with ``plain`` and says whether it helps, hurts,
makes no difference large enough to matter, or needs more seeds. docs/trial.md has the
details. The modules, by job:

- :mod:`tamrm.trial.settings`: what a trial runs (arms, seeds, settings);
- :mod:`tamrm.trial.hyperparams`: rl-zoo3's hyperparameter files;
- :mod:`tamrm.trial.run`: one run; :mod:`tamrm.trial.runner`: all of them, in parallel;
- :mod:`tamrm.trial.stats`: the statistics (shared with the paper's reproduction);
- :mod:`tamrm.trial.analysis`: metrics, comparisons, verdicts;
  :mod:`tamrm.trial.report`: the report's files;
- :mod:`tamrm.trial.cli`: the command line.
"""

from __future__ import annotations

from tamrm.trial.cli import main
from tamrm.trial.settings import ARMS, TrialSettings

__all__ = ["ARMS", "TrialSettings", "main"]
