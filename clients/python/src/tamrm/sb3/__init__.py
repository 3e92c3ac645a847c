"""Stable-Baselines3 integration (install with ``pip install 'tamrm[sb3]'``).

:class:`ShapedVecEnv` wraps an SB3 ``VecEnv`` so that the rewards the model learns from
are the shaped ones; no change to SB3 is needed::

    venv = make_vec_env("CartPole-v1", n_envs=8)
    with client.session("cartpole", venv.num_envs) as session:
        env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env)
        env.bind_model(model)  # optional: F from the model's own value estimates
        model.learn(100_000)

SB3 resets a sub-environment inside the step that ended its episode: the returned
observation is already the reset one and the real last observation is in
``infos[i]["terminal_observation"]``; ``infos[i]["TimeLimit.truncated"]`` tells a time
limit from a real termination. Both are used here: a truncated step is sent as
``truncated`` with V(s') of the real last observation, a terminated one as
``terminated`` (the server takes V(s') = 0).

Each env's ``info`` gets ``original_reward``, ``knn_reward``, ``potential``,
``shaping_step``, ``knn_active`` and ``pool_version``. Episode statistics recorded by
SB3's ``Monitor`` (below the ``VecEnv``, as ``make_vec_env`` puts it) or by a
``VecMonitor`` below this wrapper stay in terms of the original reward (``info["episode"]``,
SB3's ``ep_rew_mean``); the shaped return and its parts are beside them, in
``info["shaped_episode"]`` (``r``: the sum of R_meta, ``knn``: of alpha * r(t),
``potential``: of beta * F, ``l``: the length). A ``VecMonitor`` above this wrapper is
refused (it would record the shaped returns).

The bound model's critic is evaluated once per observation (see :class:`ModelValueFn`),
with the same values as evaluating V(s) and V(s') on every step. :class:`ShapingLogger`
records the shaped parts in the model's logger::

    model.learn(100_000, callback=tamrm.sb3.ShapingLogger())

:class:`PoolCheckpointCallback` is SB3's ``CheckpointCallback`` that also saves the task's
pool beside each model (``a2c_5000_steps.zip``, ``a2c_5000_steps.pool.jsonl``), and
:func:`restore_pool` puts a checkpoint's pool back, so that training resumed from it
shapes as if it had never stopped::

    model.learn(100_000, callback=tamrm.sb3.PoolCheckpointCallback(5_000, "ckpt", "a2c"))
    # later, in another process
    tamrm.sb3.restore_pool(client, "ckpt/a2c_5000_steps.zip")
    model = A2C.load("ckpt/a2c_5000_steps.zip", env=env)
"""

from __future__ import annotations

import importlib

try:
    # What the submodules import of SB3 (and, through it, of PyTorch).
    importlib.import_module("stable_baselines3.common.callbacks")
    importlib.import_module("stable_baselines3.common.vec_env")
except ModuleNotFoundError as _missing:  # pragma: no branch - depends on the install
    if (_missing.name or "").split(".")[0] not in ("stable_baselines3", "torch"):
        raise
    raise ImportError(
        f"tamrm.sb3 needs Stable-Baselines3 ({_missing.name} is not installed): "
        "pip install 'tamrm[sb3]' (it brings PyTorch; see docs/python.md for CPU-only "
        "wheels)",
        name=_missing.name,
    ) from None

from tamrm.sb3._checkpoint import PoolCheckpointCallback, pool_path, restore_pool
from tamrm.sb3._critic import ModelValueFn, model_value_fn
from tamrm.sb3._logger import ShapingLogger
from tamrm.sb3._vec_env import ShapedVecEnv, ShapingStats

__all__ = [
    "ModelValueFn",
    "PoolCheckpointCallback",
    "ShapedVecEnv",
    "ShapingLogger",
    "ShapingStats",
    "model_value_fn",
    "pool_path",
    "restore_pool",
]
