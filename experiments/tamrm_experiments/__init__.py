"""Reproduction of the TAMRM paper's experiments (paper §V) with tamrm's shaping.

``python -m tamrm_experiments run`` runs the grid (experiment x arm x seed), each run on
an embedded tamrm engine of its own (or on a server: ``--address``);
``python -m tamrm_experiments report`` turns the raw per-episode CSVs into
``docs/reproduction.md`` and its plots. See ``experiments/README.md``.
"""

__version__ = "0.1.0"
