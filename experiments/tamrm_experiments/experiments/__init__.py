"""The paper's experiments, one module each: setup, budgets, metrics, plot and claims."""

from __future__ import annotations

from tamrm_experiments.experiments.base import ExperimentDef
from tamrm_experiments.experiments.cartpole import CARTPOLE
from tamrm_experiments.experiments.maze import MAZE
from tamrm_experiments.experiments.maze_modified import MAZE_MODIFIED
from tamrm_experiments.experiments.mountaincar import MOUNTAINCAR

__all__ = ["EXPERIMENTS"]

#: Every experiment by name, in the report's order.
EXPERIMENTS: dict[str, ExperimentDef] = {
    exp.name: exp for exp in (CARTPOLE, MOUNTAINCAR, MAZE, MAZE_MODIFIED)
}
