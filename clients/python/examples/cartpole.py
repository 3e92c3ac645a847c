#!/usr/bin/env python3
"""Train SB3 A2C on CartPole-v0 with and without tamrm shaping, from the same seed.

Prints, for each run, how many episodes it needed until the mean return of the last 100
episodes reached 195 (CartPole-v0's "solved" threshold), with a progress bar.

    python clients/python/examples/cartpole.py                 # local server, full runs
    python clients/python/examples/cartpole.py --quick         # a few episodes (smoke test)
    python clients/python/examples/cartpole.py --server 127.0.0.1:50051

Without ``--server`` a ``tamrm`` binary is started with :func:`tamrm.local_server`
(found through ``TAMRM_BIN``, ``PATH`` or the repository's ``target/release``).
Episode returns are always the environment's own (unshaped) rewards.
"""

from __future__ import annotations

import argparse
import contextlib
import time
import uuid
import warnings
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
from stable_baselines3 import A2C
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import tamrm
import tamrm.sb3

ENV_ID = "CartPole-v0"
SOLVED = 195.0
WINDOW = 100


@dataclass
class RunResult:
    name: str
    episodes: int
    solved: bool
    best_mean: float
    last_mean: float
    timesteps: int
    seconds: float


class EpisodeTracker(BaseCallback):
    """Counts finished episodes (from Monitor's ``info["episode"]``) and stops when solved."""

    def __init__(self, max_episodes: int, bar: object | None) -> None:
        super().__init__()
        self.max_episodes = max_episodes
        self.returns: deque[float] = deque(maxlen=WINDOW)
        self.episodes = 0
        self.solved_at: int | None = None
        self.best_mean = 0.0
        self.last_mean = 0.0
        self.bar = bar

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            episode = info.get("episode")
            if episode is None:
                continue
            self.episodes += 1
            self.returns.append(float(episode["r"]))
            mean = float(np.mean(self.returns))
            self.last_mean = mean
            if len(self.returns) == WINDOW:
                self.best_mean = max(self.best_mean, mean)
            if self.bar is not None:
                self.bar.update(1)  # type: ignore[attr-defined]
                self.bar.set_postfix(mean100=f"{mean:.1f}")  # type: ignore[attr-defined]
            if len(self.returns) == WINDOW and mean >= SOLVED and self.solved_at is None:
                self.solved_at = self.episodes
                return False
            if self.episodes >= self.max_episodes:
                return False
        return True


def _progress(total: int, desc: str) -> object | None:
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit="ep", leave=True)


def train(
    name: str,
    seed: int,
    n_envs: int,
    max_episodes: int,
    client: tamrm.Client | None,
) -> RunResult:
    """One A2C run; shaped through ``client`` when given."""
    torch.manual_seed(seed)
    venv = make_vec_env(ENV_ID, n_envs=n_envs, seed=seed)
    bar = _progress(max_episodes, name)
    tracker = EpisodeTracker(max_episodes, bar)
    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        env = venv
        if client is not None:
            task_id = f"examples/cartpole/{seed}/{uuid.uuid4().hex[:8]}"
            client.create_task(task_id, num_actions=2)
            session = stack.enter_context(client.session(task_id, n_envs))
            env = tamrm.sb3.ShapedVecEnv(venv, session)
        model = A2C("MlpPolicy", env, seed=seed, device="cpu")
        if isinstance(env, tamrm.sb3.ShapedVecEnv):
            env.bind_model(model)
        model.learn(total_timesteps=10**9, callback=tracker)
        timesteps = model.num_timesteps
        env.close()
    if bar is not None:
        bar.close()  # type: ignore[attr-defined]
    return RunResult(
        name=name,
        episodes=tracker.solved_at if tracker.solved_at is not None else tracker.episodes,
        solved=tracker.solved_at is not None,
        best_mean=tracker.best_mean,
        last_mean=tracker.last_mean,
        timesteps=timesteps,
        seconds=time.perf_counter() - start,
    )


@contextlib.contextmanager
def connect(server: str | None) -> Iterator[tamrm.Client]:
    """A client of ``server``, or of a local server started for the example."""
    if server is not None:
        try:
            client = tamrm.Client(server)
        except ValueError as exc:
            raise SystemExit(f"cartpole.py: --server: {exc}") from None
        with client:
            # Check the server before training (the unshaped run comes first).
            try:
                client.list_tasks()
            except tamrm.TamrmError as exc:
                raise SystemExit(f"cartpole.py: no tamrm server at {server}: {exc}") from None
            yield client
        return
    with tamrm.local_server() as local, tamrm.Client(local.address) as client:
        yield client


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start a local one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--max-episodes", type=int, default=3000, help="give up after this many")
    parser.add_argument("--quick", action="store_true", help="smoke test: --max-episodes 20")
    ns = parser.parse_args()
    max_episodes = 20 if ns.quick else ns.max_episodes
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", message=".*CartPole-v0 is out of date.*")

    with connect(ns.server) as client:
        results = [
            train("A2C", ns.seed, ns.n_envs, max_episodes, None),
            train("A2C + tamrm", ns.seed, ns.n_envs, max_episodes, client),
        ]

    print(
        f"\n{ENV_ID}, seed {ns.seed}, {ns.n_envs} envs: "
        f"episodes to a {WINDOW}-episode mean >= {SOLVED:g}"
    )
    print(f"{'run':<14} {'episodes':>9} {'timesteps':>10} {'seconds':>8}  result")
    for r in results:
        if r.solved:
            outcome = "solved"
        else:
            outcome = (
                f"not solved in {r.episodes} episodes (last mean {r.last_mean:.1f}, "
                f"best {WINDOW}-episode mean {r.best_mean:.1f})"
            )
        print(f"{r.name:<14} {r.episodes:>9} {r.timesteps:>10} {r.seconds:>8.1f}  {outcome}")


if __name__ == "__main__":
    main()
