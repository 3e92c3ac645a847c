"""Reproduction of the TAMRM paper's experiments (paper §V) through the tamrm server.

``python -m tamrm_experiments run`` runs the grid (experiment x arm x seed) against one
local server; ``python -m tamrm_experiments report`` turns the raw per-episode CSVs into
``docs/reproduction.md`` and its plots. See ``experiments/README.md``.
"""

__version__ = "0.1.0"
