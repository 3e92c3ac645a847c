"""A task's pool exported to a file and imported from one, over a client's task calls.

The file's format is :mod:`tamrm._pool_file`'s (docs/storage.md, "Pool export format");
this module makes the calls: ``GetTask`` and ``GetPool`` to export, and to import
``GetTask``, then ``CreateTask`` (or ``DeleteTask`` and ``CreateTask``, or ``ResetPool``)
and one ``AddTrajectory`` per trajectory in ``seq`` order.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tamrm._errors import AlreadyExists, FailedPrecondition, TaskNotFound
from tamrm._pool_file import PoolFile, PoolFileLike, config_differences, read_pool_file
from tamrm._pool_file import write_pool_file as _write
from tamrm._types import Task

if TYPE_CHECKING:
    from tamrm._calls import TaskCalls, Timeout

__all__ = ["export_pool", "import_pool"]


def export_pool(calls: TaskCalls, task_id: str, file: PoolFileLike, timeout: Timeout) -> int:
    """Write the pool of ``task_id`` to ``file``; return the number of trajectories."""
    task = calls.get_task(task_id, timeout=timeout)
    pool = calls.get_pool(task_id, timeout=timeout)
    return _write(file, task, pool)


def _empty_task(
    calls: TaskCalls, task_id: str, data: PoolFile, replace: bool, timeout: Timeout
) -> Task:
    """The task ``task_id`` with the file's config and an empty pool, made so if allowed."""
    try:
        task = calls.get_task(task_id, timeout=timeout)
    except TaskNotFound:
        return calls.create_task(task_id, timeout=timeout, **data.config)
    differences = config_differences(data.config, task.config)
    if differences:
        if not replace:
            raise AlreadyExists(
                f"task {task_id!r} exists with another config than the file's "
                f"({'; '.join(differences)}); pass replace=True to delete and re-create it"
            )
        calls.delete_task(task_id, timeout=timeout)
        return calls.create_task(task_id, timeout=timeout, **data.config)
    if task.stats.pool_size > 0:
        if not replace:
            size = task.stats.pool_size
            raise FailedPrecondition(
                f"task {task_id!r} already holds {size} "
                f"{'trajectory' if size == 1 else 'trajectories'}; pass replace=True to "
                "reset its pool first"
            )
        return calls.reset_pool(task_id, timeout=timeout)
    return task


def import_pool(
    calls: TaskCalls,
    file: PoolFileLike,
    task_id: str | None,
    replace: bool,
    timeout: Timeout,
) -> Task:
    """Read ``file`` whole, then give its trajectories to an empty pool of the file's config.

    Returns the task after the import.
    """
    if not isinstance(replace, bool):
        raise TypeError(f"replace must be a bool, got {type(replace).__name__}")
    if task_id is not None and not isinstance(task_id, str):
        raise TypeError(f"task_id must be a str or None, got {type(task_id).__name__}")
    data = read_pool_file(file)
    target = data.task_id if task_id is None else task_id
    base = _empty_task(calls, target, data, replace, timeout).stats.pool_version
    count = len(data.trajectories)
    for i, t in enumerate(data.trajectories):
        added = calls.add_trajectory(target, t.actions, t.score, timeout=timeout)
        if not added.inserted or added.pool_version != base + i + 1:
            raise _changed_meanwhile(target, f"after {i} of its {count} trajectories")
    task = calls.get_task(target, timeout=timeout)
    if task.stats.pool_size != count or task.stats.pool_version != base + count:
        raise _changed_meanwhile(target, "after its last trajectory")
    return task


def _changed_meanwhile(task_id: str, when: str) -> FailedPrecondition:
    return FailedPrecondition(
        f"the pool of task {task_id!r} changed during the import ({when}): another writer "
        "(a session, another import) used the task; import again with replace=True once "
        "nothing else writes to it"
    )
