"""Self-imitation learning (Oh et al. 2018) on a Stable-Baselines3 PPO or A2C learner.

After every update of the base algorithm, ``sil_updates`` extra gradient steps on
minibatches from a buffer of the agent's own past transitions, each with its discounted
Monte-Carlo return R (from the environment's rewards, unshaped), with SIL's
clipped-advantage loss

    L = mean( -log pi(a|s) * (R - V(s))+ * w  +  0.5 * beta * ((R - V(s))+)^2 )

so only what turned out better than the critic expected is imitated. Minibatches are drawn
with probability proportional to the clipped advantage (SIL's prioritised replay, without
importance weights); transitions with none are never drawn. The buffer keeps the most
recent ``sil_capacity`` transitions of finished episodes.

``SilPPO`` / ``SilA2C`` take the base algorithm's arguments plus ``sil_updates``,
``sil_batch``, ``sil_weight`` (w), ``sil_value_coef`` (beta) and ``sil_capacity``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.vec_env import VecEnvWrapper

__all__ = ["SIL_DEFAULTS", "SilA2C", "SilPPO", "sil_class"]

#: SIL's settings as the paper's A2C+SIL uses them (M = 4, beta = 0.01, batch 512
#: there; 64 here for small envs), the starting point of the tuning grid.
SIL_DEFAULTS: dict[str, Any] = {
    "sil_updates": 4,
    "sil_batch": 64,
    "sil_weight": 1.0,
    "sil_value_coef": 0.01,
    "sil_capacity": 100_000,
}


class _EpisodeRecorder(VecEnvWrapper):
    """Records each sub-env's (obs, action, reward) and hands finished episodes over."""

    def __init__(self, venv: Any, buffer: _SilBuffer) -> None:
        super().__init__(venv)
        self.buffer = buffer
        self._obs: np.ndarray | None = None
        self._actions: np.ndarray | None = None
        self._episodes: list[list[tuple[np.ndarray, Any, float]]] = [
            [] for _ in range(venv.num_envs)
        ]

    def reset(self) -> Any:
        obs = self.venv.reset()
        self._obs = np.asarray(obs).copy()
        self._episodes = [[] for _ in range(self.num_envs)]
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).copy()
        self.venv.step_async(actions)

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        assert self._obs is not None and self._actions is not None
        for i in range(self.num_envs):
            self._episodes[i].append((self._obs[i], self._actions[i], float(rewards[i])))
            if dones[i]:
                self.buffer.add_episode(self._episodes[i])
                self._episodes[i] = []
        self._obs = np.asarray(obs).copy()
        return obs, rewards, dones, infos


class _SilBuffer:
    """The most recent transitions of finished episodes, with their discounted returns."""

    def __init__(self, capacity: int, gamma: float) -> None:
        self.capacity = capacity
        self.gamma = gamma
        self.obs: list[np.ndarray] = []
        self.actions: list[Any] = []
        self.returns: list[float] = []

    def add_episode(self, steps: list[tuple[np.ndarray, Any, float]]) -> None:
        ret = 0.0
        out = []
        for obs, action, reward in reversed(steps):
            ret = reward + self.gamma * ret
            out.append((obs, action, ret))
        for obs, action, ret in reversed(out):
            self.obs.append(obs)
            self.actions.append(action)
            self.returns.append(ret)
        extra = len(self.obs) - self.capacity
        if extra > 0:
            del self.obs[:extra], self.actions[:extra], self.returns[:extra]

    def __len__(self) -> int:
        return len(self.obs)


class _SilMixin:
    """SIL's extra updates after the base algorithm's ``train()``."""

    def _sil_setup(self, kwargs: dict[str, Any]) -> dict[str, Any]:
        settings = {k: kwargs.pop(k, v) for k, v in SIL_DEFAULTS.items()}
        self._sil = settings
        return kwargs

    def _setup_model(self) -> None:
        super()._setup_model()  # type: ignore[misc]
        self._sil_buffer = _SilBuffer(int(self._sil["sil_capacity"]), self.gamma)  # type: ignore[attr-defined]
        self.env = _EpisodeRecorder(self.env, self._sil_buffer)  # type: ignore[has-type]
        self._sil_rng = np.random.default_rng(self.seed)  # type: ignore[attr-defined]

    def train(self) -> None:
        super().train()  # type: ignore[misc]
        self._sil_train()

    def _sil_train(self) -> None:
        buffer = self._sil_buffer
        if len(buffer) == 0:
            return
        policy = self.policy  # type: ignore[attr-defined]
        policy.set_training_mode(True)
        obs_all = torch.as_tensor(np.asarray(buffer.obs), device=policy.device)
        actions_all = torch.as_tensor(np.asarray(buffer.actions), device=policy.device)
        returns_all = torch.as_tensor(
            np.asarray(buffer.returns, dtype=np.float32), device=policy.device
        )
        cfg = self._sil
        for _ in range(int(cfg["sil_updates"])):
            with torch.no_grad():
                values = policy.predict_values(obs_all).flatten()
            priority = torch.clamp(returns_all - values, min=0.0).cpu().numpy().astype(np.float64)
            total = priority.sum()
            if not total > 0:
                return
            idx = self._sil_rng.choice(
                len(priority), size=int(cfg["sil_batch"]), p=priority / total
            )
            idx_t = torch.as_tensor(idx, device=policy.device)
            obs = obs_all[idx_t]
            actions = actions_all[idx_t]
            if actions.ndim > 1 and actions.shape[-1] == 1:
                actions = actions.squeeze(-1)
            value, log_prob, _ = policy.evaluate_actions(obs, actions.long())
            advantage = returns_all[idx_t] - value.flatten()
            clipped = torch.clamp(advantage, min=0.0)
            policy_loss = -(log_prob * clipped.detach()).mean() * float(cfg["sil_weight"])
            value_loss = 0.5 * (clipped**2).mean() * float(cfg["sil_value_coef"])
            loss = policy_loss + value_loss
            policy.optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), self.max_grad_norm)  # type: ignore[attr-defined]
            policy.optimizer.step()


class SilPPO(_SilMixin, PPO):  # type: ignore[misc]
    """PPO with self-imitation learning (see the module)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **self._sil_setup(kwargs))


class SilA2C(_SilMixin, A2C):  # type: ignore[misc]
    """A2C with self-imitation learning (see the module)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **self._sil_setup(kwargs))


def sil_class(algo: str) -> type:
    """The SIL learner for a trial's ``--algo``."""
    return {"ppo": SilPPO, "a2c": SilA2C}[algo]
