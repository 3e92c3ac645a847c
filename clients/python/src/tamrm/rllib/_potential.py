"""The learner side: :class:`PotentialShaping` adds ``beta * F`` from the learner's own V(s)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Collection, Hashable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
import tree
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModule
from ray.rllib.utils.spaces.space_utils import batch as batch_structs

from tamrm._types import Task, TaskConfig
from tamrm.rllib._episodes import add_rewards

__all__ = ["POTENTIAL_MARK", "PotentialShaping", "potential_connector"]

#: The key under which :class:`PotentialShaping` marks an episode chunk it has shaped, in
#: the chunk's ``custom_data``: the (first, last + 1) agent timesteps it added F to.
POTENTIAL_MARK = "tamrm.potential_shaped"


class PotentialShaping(ConnectorV2):  # type: ignore[misc]
    """Learner ConnectorV2 piece: adds ``beta * (gamma * V(s') - V(s))`` to the rewards.

    V is the learner's own module's value function (``ValueFunctionAPI.compute_values``,
    e.g. PPO's critic), evaluated on each episode chunk's observations with the weights
    of this update. ``V(s') = 0`` after a terminated step; after a truncated step, or at
    the end of a chunk cut mid-episode, V(s') is V of the real next observation (SPEC §4,
    the ``F`` a session computes from sent values). With ``gate_potential`` F counts only
    on steps whose kNN term was active (``knn_active`` in the infos :class:`KnnShaping`
    writes), as a task with ``gate_potential=True`` computes it.

    Add it with ``config.learners(learner_connector=potential_connector(...))``: RLlib
    puts custom learner pieces before its own, so the rewards it batches (and PPO's GAE
    reads) are the shaped ones. PPO's learner prepends one artificial bootstrap step to
    each chunk; it is recognised and left unshaped.

    Once only: the piece marks each chunk it shapes (``custom_data[POTENTIAL_MARK]``,
    the agent timesteps shaped; the mark survives pickling and is not inherited by the
    chunks RLlib cuts after it) and skips a chunk that carries its own mark, so episodes
    handed to the learner again, or a second piece, add nothing; a chunk shaped over a
    different span is an error rather than a second F. It never writes into the reward
    arrays it was given (a replay buffer's episodes may share them): the shaped rewards
    are a new array. Epochs and minibatches reuse the batch built once per update.

    Args:
        input_observation_space: As for every ConnectorV2 (unused).
        input_action_space: As for every ConnectorV2 (unused).
        beta: The weight beta of F.
        gamma: The discount gamma of F.
        gate_potential: Count F only where the kNN term was active.
        modules: Only shape the episodes of these module ids (``None``: every module).
            Modules without a value function are an error unless left out here.
    """

    def __init__(
        self,
        input_observation_space: Any = None,
        input_action_space: Any = None,
        *,
        beta: float,
        gamma: float,
        gate_potential: bool = False,
        modules: Collection[Hashable] | None = None,
    ) -> None:
        super().__init__(input_observation_space, input_action_space)
        for name, value in (("beta", beta), ("gamma", gamma)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name} must be a number, got {type(value).__name__}")
            if not np.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1] (SPEC §1.1), got {gamma}")
        if not isinstance(gate_potential, bool):
            raise TypeError(f"gate_potential must be a bool, got {type(gate_potential).__name__}")
        self.beta = float(beta)
        self.gamma = float(gamma)
        self.gate_potential = gate_potential
        self.modules = None if modules is None else frozenset(modules)

    def __call__(
        self,
        *,
        rl_module: Any,
        batch: dict[str, Any],
        episodes: list[Any],
        shared_data: dict[str, Any] | None = None,
        metrics: Any = None,
        **_: Any,
    ) -> Any:
        """Add beta * F to the rewards of every chunk in ``episodes`` not shaped yet."""
        if any(isinstance(v, Mapping) and Columns.REWARDS in v for v in batch.values()) or (
            Columns.REWARDS in batch
        ):
            raise RuntimeError(
                "PotentialShaping must come before RLlib's default learner pieces: the batch "
                "already holds the rewards (use config.learners(learner_connector=...))"
            )
        # PPO's AddOneTsToEpisodesAndTruncate ran first: the last step of every chunk is
        # an artificial one for bootstrapping.
        extra = int(bool(shared_data and shared_data.get("_added_loss_mask_for_valid_episode_ts")))
        todo: dict[Any, list[tuple[Any, int]]] = {}
        for sa in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            module_id = sa.module_id if sa.module_id is not None else DEFAULT_MODULE_ID
            if self.modules is not None and module_id not in self.modules:
                continue
            steps = len(sa) - extra
            if steps <= 0:
                continue
            span = (int(sa.t_started), int(sa.t_started) + steps)
            mark = sa.custom_data.get(POTENTIAL_MARK)
            if mark is not None and tuple(mark) == span:
                continue
            if mark is not None and mark[0] < span[1] and span[0] < mark[1]:
                raise RuntimeError(
                    f"episode {sa.id_!r} (agent {sa.agent_id!r}): its agent steps "
                    f"{mark[0]}..{mark[1] - 1} already carry beta * F, and this chunk spans "
                    f"{span[0]}..{span[1] - 1}; refusing to add F twice"
                )
            todo.setdefault(module_id, []).append((sa, steps))
        total = 0.0
        count = 0
        for module_id, items in todo.items():
            values = self._values(rl_module, module_id, items)
            offset = 0
            for sa, steps in items:
                v = values[offset : offset + steps + 1].copy()
                offset += steps + 1
                if sa.is_terminated:
                    v[steps] = 0.0
                potential = self.gamma * v[1:] - v[:-1]
                if self.gate_potential:
                    potential *= self._knn_active(sa, steps)
                shaped = self.beta * potential
                add_rewards(sa, shaped)
                sa.custom_data[POTENTIAL_MARK] = (int(sa.t_started), int(sa.t_started) + steps)
                total += float(shaped.sum())
                count += steps
        if metrics is not None and count:
            metrics.log_value(("tamrm", "beta_potential_mean"), total / count, window=1)
        return batch

    def _values(
        self, rl_module: Any, module_id: Any, items: list[tuple[Any, int]]
    ) -> npt.NDArray[np.float64]:
        """V(o_0..o_n) of every chunk in ``items``, concatenated, from one forward pass."""
        import torch
        from ray.rllib.utils.torch_utils import convert_to_torch_tensor

        module = rl_module[module_id] if isinstance(rl_module, MultiRLModule) else rl_module
        if not isinstance(module, ValueFunctionAPI):
            raise TypeError(
                f"module {module_id!r} ({type(module).__name__}) has no value function "
                "(ValueFunctionAPI): PotentialShaping needs V(s); leave the module out "
                "with modules=..."
            )
        if module.is_stateful():
            raise NotImplementedError(
                f"module {module_id!r} is stateful (recurrent): PotentialShaping computes "
                "V(s) of stateless modules only"
            )
        parts = []
        for sa, steps in items:
            obs = sa.get_observations(slice(0, steps + 1))
            parts.append(batch_structs(obs) if isinstance(obs, list) else obs)
        obs_batch = tree.map_structure(lambda *xs: np.concatenate(xs, axis=0), *parts)
        params = list(module.parameters()) if hasattr(module, "parameters") else []
        device = params[0].device if params else None
        with torch.no_grad():
            tensor = convert_to_torch_tensor(obs_batch, device=device)
            out = module.compute_values({Columns.OBS: tensor})
        values = np.asarray(out.detach().cpu().numpy(), dtype=np.float64).reshape(-1)
        expected = sum(steps + 1 for _, steps in items)
        if values.shape[0] != expected:
            raise ValueError(
                f"module {module_id!r}: compute_values returned {values.shape[0]} values for "
                f"{expected} observations"
            )
        return values

    def _knn_active(self, sa: Any, steps: int) -> npt.NDArray[np.float64]:
        infos = sa.get_infos(slice(1, steps + 1))
        flags = np.zeros(steps, dtype=np.float64)
        for k, info in enumerate(infos):
            if "knn_active" not in info:
                raise ValueError(
                    f"gate_potential: step {sa.t_started + k} of episode {sa.id_!r} has no "
                    "'knn_active' info; the EnvRunners must run KnnShaping"
                )
            flags[k] = float(bool(info["knn_active"]))
        return flags


def _build_potential(
    input_observation_space: Any = None,
    input_action_space: Any = None,
    device: Any = None,
    *,
    options: dict[str, Any],
) -> PotentialShaping:
    return PotentialShaping(input_observation_space, input_action_space, **options)


def potential_connector(
    task: Task | TaskConfig | None = None,
    *,
    beta: float | None = None,
    gamma: float | None = None,
    gate_potential: bool | None = None,
    modules: Collection[Hashable] | None = None,
) -> Callable[..., PotentialShaping]:
    """A builder for ``config.learners(learner_connector=...)``.

    ``beta``, ``gamma`` and ``gate_potential`` default to ``task``'s (a :class:`tamrm.Task`
    from ``client.get_task`` or its ``config``), so that F is the one the task would
    compute from sent values; without a task give ``beta`` and ``gamma``.

    Raises:
        TypeError, ValueError: Missing or bad values (checked here, on the driver).
    """
    config = task.config if isinstance(task, Task) else task
    if config is not None and not isinstance(config, TaskConfig):
        raise TypeError(f"task must be a tamrm.Task or TaskConfig, got {type(task).__name__}")
    if beta is None:
        if config is None:
            raise TypeError("potential_connector needs beta (or a task to take it from)")
        beta = config.beta
    if gamma is None:
        if config is None:
            raise TypeError("potential_connector needs gamma (or a task to take it from)")
        gamma = config.gamma
    if gate_potential is None:
        gate_potential = bool(config.gate_potential) if config is not None else False
    options: dict[str, Any] = {
        "beta": beta,
        "gamma": gamma,
        "gate_potential": gate_potential,
        "modules": None if modules is None else frozenset(modules),
    }
    PotentialShaping(**options)
    return functools.partial(_build_potential, options=options)
