"""Python client of tamrm, the trajectory action meta-reward model (TAMRM) shaping service.

The server keeps, per task, a pool of the best past episodes and shapes every
environment reward into ``R_meta = R + alpha * r(t) + beta * F``: ``r(t)`` rewards an
episode whose action prefix resembles the best stored episodes (k nearest neighbours),
``F = gamma * V(s') - V(s)`` is a potential term from the learner's own value estimates.

Main entry points:

- :class:`Engine`: the shaping engine in-process (no server), the default for one learner.
- :class:`Client` (and :mod:`tamrm.aio` for asyncio): the same methods against a server.
- :meth:`Client.session` -> :class:`Session`: one stream, one round trip per vector step.
- :meth:`Client.export_pool` / :meth:`Client.import_pool`: a task's pool to a file and back.
- :mod:`tamrm.gym`: ``ShapedReward`` / ``VectorShapedReward`` gymnasium wrappers.
- :mod:`tamrm.sb3`: ``ShapedVecEnv`` for Stable-Baselines3 (extra ``tamrm[sb3]``).
- :mod:`tamrm.pettingzoo`: ``ShapedParallel`` / ``ShapedAEC`` for PettingZoo
  multi-agent envs (extra ``tamrm[pettingzoo]``).
- :mod:`tamrm.rllib`: connectors that shape Ray RLlib's EnvRunners and add the potential
  term on its learners (extra ``tamrm[rllib]``).
- :func:`local_server`: run a ``tamrm`` binary on a free port for tests and examples.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from tamrm import _bridge
from tamrm._address import DEFAULT_ADDRESS
from tamrm._calls import DEFAULT_TIMEOUT
from tamrm._client import Client
from tamrm._connection import ConnectionOptions
from tamrm._engine import Engine
from tamrm._errors import (
    AlreadyExists,
    DeadlineExceeded,
    FailedPrecondition,
    InvalidArgument,
    PermissionDenied,
    ResourceExhausted,
    SessionClosed,
    StatusCode,
    TamrmError,
    TaskNotFound,
    Unauthenticated,
    Unavailable,
)
from tamrm._pool_file import PoolFileError
from tamrm._server import LocalServer, ServerStartError, find_binary, local_server
from tamrm._session import Session
from tamrm._types import (
    CONFIG_FIELDS,
    AddTrajectoryResult,
    Pool,
    StepResult,
    Task,
    TaskConfig,
    TaskOptions,
    TaskStats,
    Trajectory,
)

if TYPE_CHECKING:
    import tamrm.aio as aio
    import tamrm.gym as gym
    import tamrm.pettingzoo as pettingzoo
    import tamrm.rllib as rllib
    import tamrm.sb3 as sb3

__version__: str = _bridge.VERSION

__all__ = [
    "CONFIG_FIELDS",
    "DEFAULT_ADDRESS",
    "DEFAULT_TIMEOUT",
    "AddTrajectoryResult",
    "AlreadyExists",
    "Client",
    "ConnectionOptions",
    "DeadlineExceeded",
    "PermissionDenied",
    "Unauthenticated",
    "Engine",
    "FailedPrecondition",
    "InvalidArgument",
    "LocalServer",
    "Pool",
    "PoolFileError",
    "ResourceExhausted",
    "ServerStartError",
    "Session",
    "SessionClosed",
    "StatusCode",
    "StepResult",
    "TamrmError",
    "Task",
    "TaskConfig",
    "TaskNotFound",
    "TaskOptions",
    "TaskStats",
    "Trajectory",
    "Unavailable",
    "__version__",
    "aio",
    "find_binary",
    "gym",
    "local_server",
    "pettingzoo",
    "rllib",
    "sb3",
]

_LAZY = {"aio", "gym", "pettingzoo", "rllib", "sb3"}


def __getattr__(name: str) -> Any:
    """Import an optional submodule (``aio``, ``gym``, ``pettingzoo``, ``rllib``...) on use."""
    if name in _LAZY:
        module = importlib.import_module(f"tamrm.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module 'tamrm' has no attribute {name!r}")
