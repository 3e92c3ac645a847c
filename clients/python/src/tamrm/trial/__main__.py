"""``python -m tamrm.trial``: the same as ``tamrm-trial``."""

import sys

from tamrm.trial.cli import main

sys.exit(main())
