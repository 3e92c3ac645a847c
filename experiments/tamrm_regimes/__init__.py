"""The regime study: where TAMRM's shaping helps, given its best honest chance.

docs/regimes/plan.md is the plan, committed before the confirmatory runs;
docs/regimes.md the results. ``python -m tamrm_regimes --help`` runs and reports.
"""
