"""The authors' learners, transcribed from their TensorFlow code into numpy.

The authors' code (github.com/skykobe/Research-Planning-of-Master-s-Thesis,
``meta_reward_model/``) uses two small learners; the ``authors`` fidelity of the
reproduction runs these transcriptions (the ``clean`` fidelity runs Stable-Baselines3):

- :class:`ActorCritic` (``Carpole_test/carpole.py``): a one-step actor-critic. Actor and
  critic are MLPs with one hidden layer of 20 ReLU units (weights N(0, 0.1), biases 0.1);
  the actor's softmax policy is trained on ``-log pi(a|s) * td`` with Adam 1e-3, the
  critic on ``td**2`` with Adam 1e-2, where ``td = r + gamma V(s') - V(s)``, gamma 0.9,
  V(s') taken as given (no terminal mask, as theirs). :meth:`ActorCritic.freeze` sets the
  actor's learning rate to 1e-5 (theirs, once the task is solved).
- :class:`TutorialDQN` (``MountainCar_test/RL_brain.py``, ``prioritized=False``): one hidden
  layer of 20 ReLU units (weights N(0, 0.3), biases 0.1), RMSProp 0.005 (TensorFlow 1's:
  decay 0.9, no momentum, epsilon 1e-10, mean-square accumulator starting at 1), mean
  squared error over the whole Q row of a batch of 32 (the target equals Q except at the
  taken action), gamma 0.9, no terminal mask in the target, target network copied every
  500 learning steps (also before the first), a 50 000-transition ring buffer sampled
  uniformly over its whole capacity, learning on every step once more than 50 000 steps
  were taken, and a greedy probability that starts at 0 and grows by 5e-5 per learning
  step up to 0.9 (epsilon 1 -> 0.1). Their maze (``Maze_grid/RL_brain.py``, ``DeepQNetwork``)
  is the same DQN with 10 hidden units, Adam 0.01, a 20 000-transition buffer, the target
  copied every 200 learning steps and a fixed greedy probability of 0.9
  (``optimizer="adam"``, ``greedy_increment=None``).

Both take a ``numpy.random.Generator`` so that a run is reproducible from its seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MLP", "ActorCritic", "Adam", "RMSPropTF1", "TutorialDQN"]

Array = np.ndarray


@dataclass
class MLP:
    """``x -> relu(x W1 + b1) W2 + b2``: one hidden layer, float64."""

    w1: Array
    b1: Array
    w2: Array
    b2: Array

    @classmethod
    def init(cls, rng: np.random.Generator, n_in: int, n_hidden: int, n_out: int, std: float):
        """Weights N(0, std), biases 0.1 (the authors' initialisers)."""
        return cls(
            rng.normal(0.0, std, (n_in, n_hidden)),
            np.full(n_hidden, 0.1),
            rng.normal(0.0, std, (n_hidden, n_out)),
            np.full(n_out, 0.1),
        )

    def params(self) -> list[Array]:
        """The parameters, in a fixed order (updated in place by the optimisers)."""
        return [self.w1, self.b1, self.w2, self.b2]

    def copy(self) -> MLP:
        """A deep copy (a target network)."""
        return MLP(*(p.copy() for p in self.params()))

    def load(self, other: MLP) -> None:
        """Copy ``other``'s parameters into this network."""
        for dst, src in zip(self.params(), other.params(), strict=True):
            dst[...] = src

    def forward(self, x: Array) -> tuple[Array, Array]:
        """Return (output, hidden activations) for a batch ``x`` of shape (B, n_in)."""
        h = np.maximum(x @ self.w1 + self.b1, 0.0)
        return h @ self.w2 + self.b2, h

    def __call__(self, x: Array) -> Array:
        return self.forward(x)[0]

    def backward(self, x: Array, h: Array, grad_out: Array) -> list[Array]:
        """Gradients of a loss w.r.t. the parameters, given d loss / d output."""
        gh = (grad_out @ self.w2.T) * (h > 0)
        return [x.T @ gh, gh.sum(0), h.T @ grad_out, grad_out.sum(0)]


@dataclass
class Adam:
    """Adam with TensorFlow 1's defaults (beta1 0.9, beta2 0.999, epsilon 1e-8)."""

    params: list[Array]
    lr: float
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    t: int = 0
    m: list[Array] = field(default_factory=list)
    v: list[Array] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.m = [np.zeros_like(p) for p in self.params]
        self.v = [np.zeros_like(p) for p in self.params]

    def step(self, grads: list[Array]) -> None:
        """One descent step (TensorFlow's form: bias correction folded into the rate)."""
        self.t += 1
        lr_t = self.lr * np.sqrt(1 - self.b2**self.t) / (1 - self.b1**self.t)
        for p, g, m, v in zip(self.params, grads, self.m, self.v, strict=True):
            m *= self.b1
            m += (1 - self.b1) * g
            v *= self.b2
            v += (1 - self.b2) * g * g
            p -= lr_t * m / (np.sqrt(v) + self.eps)


@dataclass
class RMSPropTF1:
    """TensorFlow 1's ``RMSPropOptimizer`` (decay 0.9, momentum 0, epsilon 1e-10; the
    mean-square accumulator starts at 1, not 0)."""

    params: list[Array]
    lr: float
    decay: float = 0.9
    eps: float = 1e-10
    ms: list[Array] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.ms = [np.ones_like(p) for p in self.params]

    def step(self, grads: list[Array]) -> None:
        """One descent step."""
        for p, g, ms in zip(self.params, grads, self.ms, strict=True):
            ms *= self.decay
            ms += (1 - self.decay) * g * g
            p -= self.lr * g / np.sqrt(ms + self.eps)


def _softmax(z: Array) -> Array:
    e = np.exp(z - z.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


class ActorCritic:
    """The authors' one-step actor-critic (cart pole); see the module docstring."""

    def __init__(
        self,
        n_features: int,
        n_actions: int,
        rng: np.random.Generator,
        *,
        lr_actor: float = 1e-3,
        lr_critic: float = 1e-2,
        gamma: float = 0.9,
        hidden: int = 20,
    ) -> None:
        self.rng = rng
        self.gamma = gamma
        self.actor = MLP.init(rng, n_features, hidden, n_actions, 0.1)
        self.critic = MLP.init(rng, n_features, hidden, 1, 0.1)
        self.actor_opt = Adam(self.actor.params(), lr_actor)
        self.critic_opt = Adam(self.critic.params(), lr_critic)

    def probs(self, s: Array) -> Array:
        """pi(. | s)."""
        return _softmax(self.actor(np.asarray(s, dtype=np.float64)[None]))[0]

    def act(self, s: Array) -> int:
        """Sample an action from pi(. | s)."""
        p = self.probs(s)
        return int(self.rng.choice(p.size, p=p))

    def value(self, s: Array) -> float:
        """The critic's V(s)."""
        return float(self.critic(np.asarray(s, dtype=np.float64)[None])[0, 0])

    def learn(self, s: Array, a: int, r: float, s_next: Array) -> float:
        """One step of both: returns the TD error (before the critic's update) that the
        actor's update uses, as the authors' ``critic.learn`` does."""
        x = np.asarray(s, dtype=np.float64)[None]
        v_next = self.value(s_next)
        v, h = self.critic.forward(x)
        td = float(r + self.gamma * v_next - v[0, 0])
        # d td^2 / d V(s) = -2 td
        self.critic_opt.step(self.critic.backward(x, h, np.array([[-2.0 * td]])))
        logits, ha = self.actor.forward(x)
        p = _softmax(logits)
        # loss = -log(p_a + 1e-8) * td; d loss / d logits = -td * p_a / (p_a + 1e-8) * (e_a - p)
        onehot = np.zeros_like(p)
        onehot[0, a] = 1.0
        pa = p[0, a]
        grad = -td * (pa / (pa + 1e-8)) * (onehot - p)
        self.actor_opt.step(self.actor.backward(x, ha, grad))
        return td

    def freeze(self) -> None:
        """The authors' "solved" rule: the actor's learning rate drops to 1e-5."""
        self.actor_opt.lr = 1e-5


class TutorialDQN:
    """The authors' DQN (mountain car); see the module docstring."""

    def __init__(
        self,
        n_features: int,
        n_actions: int,
        rng: np.random.Generator,
        *,
        lr: float = 0.005,
        gamma: float = 0.9,
        greedy_max: float = 0.9,
        greedy_increment: float | None = 5e-5,
        replace_target_iter: int = 500,
        memory_size: int = 50_000,
        batch_size: int = 32,
        hidden: int = 20,
        learn_after: int | None = None,
        optimizer: str = "rmsprop",
    ) -> None:
        self.rng = rng
        self.n_actions = n_actions
        self.n_features = n_features
        self.gamma = gamma
        # No increment (their maze): greedy with probability greedy_max from the start.
        self.greedy = 0.0 if greedy_increment else greedy_max
        self.greedy_max = greedy_max
        self.greedy_increment = greedy_increment or 0.0
        self.replace_target_iter = replace_target_iter
        self.batch_size = batch_size
        self.memory = np.zeros((memory_size, 2 * n_features + 2))
        self.memory_counter = 0
        self.learn_after = memory_size if learn_after is None else learn_after
        self.learn_steps = 0
        self.steps = 0
        self.q = MLP.init(rng, n_features, hidden, n_actions, 0.3)
        self.target = self.q.copy()
        self.opt: Adam | RMSPropTF1 = (
            Adam(self.q.params(), lr) if optimizer == "adam" else RMSPropTF1(self.q.params(), lr)
        )

    @property
    def epsilon(self) -> float:
        """The probability of a random action."""
        return 1.0 - self.greedy

    def q_values(self, s: Array) -> Array:
        """Q(s, .) of the online network."""
        return self.q(np.asarray(s, dtype=np.float64)[None])[0]

    def target_q_values(self, s: Array) -> Array:
        """Q(s, .) of the target network."""
        return self.target(np.asarray(s, dtype=np.float64)[None])[0]

    def act(self, s: Array) -> int:
        """Greedy with probability ``greedy``, else uniform."""
        if self.rng.uniform() < self.greedy:
            return int(np.argmax(self.q_values(s)))
        return int(self.rng.integers(self.n_actions))

    def observe(self, s: Array, a: int, r: float, s_next: Array) -> None:
        """Store the transition, then learn once if more than ``learn_after`` steps were
        taken (the authors' ``total_steps > MEMORY_SIZE``, counted before this step)."""
        row = np.concatenate([np.asarray(s, np.float64), [a, r], np.asarray(s_next, np.float64)])
        self.memory[self.memory_counter % self.memory.shape[0]] = row
        self.memory_counter += 1
        if self.steps > self.learn_after:
            self.learn()
        self.steps += 1

    def learn(self) -> float:
        """One gradient step on a uniform batch; returns the loss."""
        if self.learn_steps % self.replace_target_iter == 0:
            self.target.load(self.q)
        idx = self.rng.integers(self.memory.shape[0], size=self.batch_size)
        batch = self.memory[idx]
        nf = self.n_features
        s, a = batch[:, :nf], batch[:, nf].astype(int)
        r, s_next = batch[:, nf + 1], batch[:, -nf:]
        q_next = self.target(s_next)
        q, h = self.q.forward(s)
        target = q.copy()
        rows = np.arange(self.batch_size)
        target[rows, a] = r + self.gamma * q_next.max(axis=1)
        diff = q - target
        loss = float(np.mean(diff**2))
        self.opt.step(self.q.backward(s, h, 2.0 * diff / diff.size))
        self.greedy = min(self.greedy + self.greedy_increment, self.greedy_max)
        self.learn_steps += 1
        return loss
