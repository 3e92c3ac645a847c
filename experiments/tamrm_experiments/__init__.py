"""Reproduction of the TAMRM paper's experiments (paper §V) with tamrm's shaping.

``python -m tamrm_experiments run`` runs the grid (experiment x arm x seed), each run on
an embedded tamrm engine of its own (or on a server: ``--address``);
``python -m tamrm_experiments add-runs`` records its finished runs in the committed archive
(``docs/reproduction/runs/``, one gzipped JSON file per run); ``python -m tamrm_experiments
report`` turns the raw runs into ``docs/reproduction.md``, its plots and the README's
summary. See ``experiments/README.md``.
"""

__version__ = "0.1.0"
