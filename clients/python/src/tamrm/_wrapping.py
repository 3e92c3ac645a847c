"""What the gymnasium and Stable-Baselines3 wrappers share: checks and session ownership."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from tamrm._session import Session
from tamrm._types import TaskConfig

__all__ = ["check_action_space", "check_session", "close_session"]


def check_action_space(space: spaces.Space[Any], config: TaskConfig) -> None:
    """Check that an action space matches a task's configuration.

    Raises:
        ValueError: A discrete task with a non-``Discrete(num_actions)`` space (starting at
            0), or a continuous task with a space whose flat size is not ``action_dim``.
    """
    if config.discrete:
        if not isinstance(space, spaces.Discrete):
            raise ValueError(
                f"task has num_actions={config.num_actions} but the action space is {space}"
            )
        if int(space.n) != config.num_actions or int(space.start) != 0:
            raise ValueError(
                f"task has num_actions={config.num_actions} but the action space is {space} "
                "(need Discrete(num_actions) starting at 0)"
            )
    else:
        if not isinstance(space, spaces.Box) or int(np.prod(space.shape)) != config.action_dim:
            raise ValueError(
                f"task has action_dim={config.action_dim} but the action space is {space}"
            )


def check_session(
    session: Session, num_envs: int, action_space: spaces.Space[Any], what: str
) -> None:
    """Check that a session fits a vector environment (``what`` names it in the message).

    Raises:
        ValueError: The numbers of environments differ, or see :func:`check_action_space`.
    """
    if session.num_envs != num_envs:
        raise ValueError(f"session has num_envs={session.num_envs} but {what} has {num_envs}")
    check_action_space(action_space, session.config)


def close_session(session: Session, close: bool | None) -> None:
    """Close a wrapper's session on the wrapper's ``close()`` if the wrapper owns it.

    ``close`` is the wrapper's ``close_session`` argument: ``True`` / ``False`` decide;
    ``None`` (the default) closes the session unless it is open in a ``with`` block,
    which owns it then. A session made by unpickling (the copy of a wrapper in a worker
    process) is always the wrapper's own.
    """
    if session._unpickled or (close is None and not session._in_with) or close:
        session.close()
