"""``python -m tamrm_regimes``: run a stage of the study, or write its report."""

from tamrm_regimes.cli import main

raise SystemExit(main())
