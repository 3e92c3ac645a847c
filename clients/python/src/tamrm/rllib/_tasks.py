"""Which task an agent's episodes are shaped on (:data:`TaskMap`), checked."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["TaskMap", "check_task_map", "task_of"]

#: Which task an agent's episodes are shaped on: one task id for every agent, or a
#: function ``agent_id -> task id`` (per agent, role or team, like ``policy_mapping_fn``).
TaskMap = str | Callable[[Any], str]


def task_of(task: TaskMap, agent_id: Any) -> str:
    """The task id of ``agent_id`` (checked)."""
    if isinstance(task, str):
        return task
    task_id = task(agent_id)
    if not isinstance(task_id, str):
        raise TypeError(
            f"the task function returned {task_id!r} for agent {agent_id!r}; "
            "it must return a task id (str)"
        )
    return task_id


def check_task_map(task: object) -> None:
    if isinstance(task, str):
        if not task:
            raise ValueError("task must be a non-empty task id")
    elif not callable(task):
        raise TypeError(
            f"task must be a task id (str) or a function agent_id -> task id, "
            f"got {type(task).__name__}"
        )
