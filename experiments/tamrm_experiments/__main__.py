"""``python -m tamrm_experiments {run,report}``."""

from tamrm_experiments.cli import main

raise SystemExit(main())
