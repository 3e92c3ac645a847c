#!/usr/bin/env python3
"""Measure what shaping through tamrm costs a training loop.

Workloads:

1. A 16-env CartPole-v1 gymnasium vector loop (random actions), plain and shaped with
   ``VectorShapedReward`` (no values; ``--value-fn`` adds runs with a small numpy linear
   critic, so that the cost measured is tamrm's, not a network's).
2. A Stable-Baselines3 A2C ``learn()`` on CartPole-v1 (8 envs, a fixed number of
   timesteps), plain and through ``ShapedVecEnv`` with the model's own values bound
   (``bind_model``), in two forms (``--a2c-weights``): with alpha = beta = 0, where the
   learner gets the plain run's rewards and learns the same weights (checked), so the
   difference is what shaping costs; and with the SPEC's default weights, where it also
   learns differently.

Variants (shaping backends): ``plain`` (no shaping), ``engine`` (``tamrm.Engine()``, in
memory), ``engine-dir`` (``tamrm.Engine(data_dir)``, durable), ``remote`` (``tamrm.Client``
to a local server without ``--data-dir``), ``remote-poll`` (the same with
``busy_poll_us=200``), ``remote-poll-1t`` (that, and the server with
``--worker-threads 1``) and ``remote-dir`` (to a local server with ``--data-dir``),
``local`` and ``local-dir`` (the same servers, sessions opened with ``local=True``: steps
shaped in-process against a followed pool, only episode ends sent; the run also prints the
messages the servers received per env step, from their metrics), ``local-far`` and
``remote-far`` (``local-dir`` and ``remote-dir`` with the server "on another machine": a
proxy process, ``slow_proxy.py``, delays each direction by ``--far-ms``); with
``--server ADDR`` the remote variants are replaced by one, ``server``, on that address.
Each run uses a fresh task (created before, deleted after the timing). ``tcp-floor`` is
the floor of every remote variant: no shaping, but one TCP round trip per vector step, of
the size of a step's batch and answer, to a C echo on 127.0.0.1 (``tcp_echo.c``, built
with the system C compiler): what any remote service costs at least on this machine,
with no gRPC and no work in the peer. Two variants split the Engine's cost:
``wrapper-floor`` shapes nothing and does no I/O, it only wraps the env (in A2C an SB3
``VecEnvWrapper`` that writes ``ShapedVecEnv``'s six info keys with constants; in the loop
a pass-through gymnasium ``VectorWrapper``), and ``engine-novalues`` is ``engine`` without
``bind_model`` (no critic evaluated, F = 0).

Every variant is run once as a warm-up, then ``--repeats`` times, **interleaved**: each
repeat runs every variant once, in an order rotated by one each repeat, so that the
machine's load drifts over all variants alike. The A2C runs go further (``--a2c-turn``,
:func:`a2c_turns`): in each repeat every variant's model is built in one process and they
learn in turns of 400 timesteps (about a quarter of a second), so that even the drift of
this machine's speed within a run, tens of percent over seconds, falls on all alike.
The table (markdown, to paste into docs/python-performance.md) gives per workload and
variant the median time, the throughput, the median over repeats of the overhead against
that repeat's plain run, and the overhead per vector step::

    python clients/python/benchmarks/overhead.py            # full (5 repeats)
    python clients/python/benchmarks/overhead.py --quick    # a fast smoke run
    python clients/python/benchmarks/overhead.py --repeats 3 --variants plain,engine
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import tamrm
import tamrm.gym

# SB3 makes a new log dir under the temp dir at every learn() unless $SB3_LOGDIR names
# one; its loggers here print at most, so thousands of turns would leave thousands of
# empty dirs behind. One dir for every run of these scripts instead.
os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "tamrm-sb3-logs"))

VARIANTS = (
    "plain",
    "engine",
    "engine-dir",
    "remote",
    "remote-poll",
    "remote-poll-1t",
    "remote-dir",
    "local",
    "local-dir",
    "local-far",
    "remote-far",
    "tcp-floor",
    "wrapper-floor",
    "engine-novalues",
)
#: ``busy_poll_us`` of the ``remote-poll`` variant.
BUSY_POLL_US = 200
LABELS = {
    "tcp-floor": "floor: a TCP round trip to an echo, no shaping",
    "plain": "no shaping",
    "engine": "Engine, in memory",
    "engine-dir": "Engine, data dir",
    "engine-novalues": "Engine, in memory, no values bound",
    "wrapper-floor": "floor: a pass-through wrapper, no shaping",
    "remote": "Client, server in memory",
    "remote-poll": f"Client(busy_poll_us={BUSY_POLL_US}), server in memory",
    "remote-poll-1t": f"Client(busy_poll_us={BUSY_POLL_US}), server in memory, --worker-threads 1",
    "remote-dir": "Client, server --data-dir",
    "local": "Client session(local=True), server in memory",
    "local-dir": "Client session(local=True), server --data-dir",
    "local-far": "Client session(local=True), server --data-dir, {far}",
    "remote-far": "Client, server --data-dir, {far}",
    "server": "Client, --server",
}

# A shaping backend: tamrm.Engine or tamrm.Client (None: no shaping).
Backend = Any
#: Per ``Local`` backend: env steps its server counted over the runs so far.
STEPS_SHAPED: dict[Any, int] = {}


class TcpFloor:
    """The ``tcp-floor`` variant: a C echo process (``tcp_echo.c``) on 127.0.0.1; each run
    opens a connection and makes one round trip per vector step."""

    #: Bytes per env each way: a step's batch is about 28 bytes per env on the wire (env id,
    #: action, reward, two flags, two values), its answer about 27 (reward, kNN reward,
    #: potential, step, flag), plus a few bytes of message header.
    BYTES_PER_ENV = 28
    HEADER = 32

    def __init__(self, tmp: str) -> None:
        exe = os.path.join(tmp, "tcp_echo")
        source = Path(__file__).with_name("tcp_echo.c")
        cc = os.environ.get("CC", "cc")
        subprocess.run([cc, "-O2", "-o", exe, str(source)], check=True)
        self._proc = subprocess.Popen([exe], stdout=subprocess.PIPE, text=True)
        assert self._proc.stdout is not None
        self.port = int(self._proc.stdout.readline())

    def close(self) -> None:
        self._proc.kill()
        self._proc.wait()

    @contextlib.contextmanager
    def round_trips(self, num_envs: int) -> Iterator[Callable[[], None]]:
        """A connection; yields the function that makes one round trip on it."""
        sock = socket.create_connection(("127.0.0.1", self.port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        payload = bytes(self.HEADER + self.BYTES_PER_ENV * num_envs)
        buf = bytearray(len(payload))
        view = memoryview(buf)

        def round_trip() -> None:
            sock.sendall(payload)
            got = 0
            while got < len(buf):
                n = sock.recv_into(view[got:])
                if n == 0:
                    raise ConnectionError("tcp_echo closed the connection")
                got += n

        try:
            yield round_trip
        finally:
            sock.close()


class Local:
    """The ``local`` variants: a :class:`tamrm.Client` whose sessions are local (SPEC §13),
    and the address of its server's metrics."""

    def __init__(self, client: tamrm.Client, metrics: str) -> None:
        self.client = client
        self.metrics = metrics

    def create_task(self, task_id: str, **config: Any) -> Any:
        return self.client.create_task(task_id, **config)

    def delete_task(self, task_id: str) -> None:
        self.client.delete_task(task_id)

    def session(self, task_id: str, num_envs: int) -> tamrm.Session:
        return self.client.session(task_id, num_envs, local=True)

    def messages_received(self) -> float:
        """Messages the server received on Follow streams so far (its metrics)."""
        import urllib.request

        with urllib.request.urlopen(f"http://{self.metrics}/metrics") as r:
            text = r.read().decode()
        return sum(
            float(line.rsplit(" ", 1)[1])
            for line in text.splitlines()
            if line.startswith("grpc_server_msg_received_total") and 'grpc_method="Follow"' in line
        )


@contextlib.contextmanager
def slow_path(target: str, delay_ms: float) -> Iterator[str]:
    """A ``slow_proxy.py`` process in front of ``target``; yields its address."""
    script = Path(__file__).with_name("slow_proxy.py")
    args = [sys.executable, str(script), target, "--delay-ms", str(delay_ms)]
    with subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) as p:
        assert p.stdin is not None and p.stdout is not None
        try:
            yield p.stdout.readline().strip()
        finally:
            p.stdin.close()
            p.wait(10)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class WrapperFloor:
    """The ``wrapper-floor`` variant (see the module's docstring): no backend at all."""


class NoValues:
    """The ``engine-novalues`` variant: ``engine`` (an in-memory Engine), no values bound."""

    def __init__(self, engine: tamrm.Engine) -> None:
        self.engine = engine


def _vector_env(num_envs: int) -> gym.vector.SyncVectorEnv:
    return gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1") for _ in range(num_envs)])


def _linear_value(obs: Any) -> np.ndarray:
    return np.asarray(obs, dtype=np.float64) @ np.array([0.1, -0.2, 0.3, 0.05])


@contextlib.contextmanager
def _shaped(
    backend: Backend | None, num_envs: int, **config: float
) -> Iterator[tamrm.Session | None]:
    if backend is None:
        yield None
        return
    task_id = f"bench/{uuid.uuid4().hex[:12]}"
    backend.create_task(task_id, num_actions=2, **config)
    try:
        with backend.session(task_id, num_envs) as session:
            yield session
        if isinstance(backend, Local):
            STEPS_SHAPED[backend] = STEPS_SHAPED.get(backend, 0) + (
                backend.client.get_task(task_id).stats.steps_shaped
            )
    finally:
        backend.delete_task(task_id)


def vector_loop(backend: Backend | None, num_envs: int, steps: int, with_values: bool) -> float:
    """Seconds for ``steps`` vector steps of ``num_envs`` CartPoles."""
    actions = np.random.default_rng(0).integers(0, 2, size=(steps, num_envs))
    if isinstance(backend, NoValues):
        backend, with_values = backend.engine, False
    with contextlib.ExitStack() as stack:
        env: gym.vector.VectorEnv = _vector_env(num_envs)
        after_step: Callable[[], None] = lambda: None  # noqa: E731
        if isinstance(backend, WrapperFloor):
            env = gym.vector.VectorWrapper(env)
        elif isinstance(backend, TcpFloor):
            after_step = stack.enter_context(backend.round_trips(num_envs))
        elif (session := stack.enter_context(_shaped(backend, num_envs))) is not None:
            env = tamrm.gym.VectorShapedReward(
                env, session, value_fn=_linear_value if with_values else None
            )
        env.reset(seed=0)
        start = time.perf_counter()
        for t in range(steps):
            env.step(actions[t])
            after_step()
        elapsed = time.perf_counter() - start
        env.close()
    return elapsed


def _round_trip_per_step(venv: Any, round_trip: Callable[[], None] | None) -> Any:
    """``venv`` (an SB3 VecEnv) making one ``round_trip`` after every step; without one,
    writing ``ShapedVecEnv``'s six info keys (constants) instead."""
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class RoundTripPerStep(VecEnvWrapper):  # type: ignore[misc]
        def reset(self) -> Any:
            return self.venv.reset()

        def step_wait(self) -> Any:
            out = self.venv.step_wait()
            if round_trip is not None:
                round_trip()
                return out
            for info, reward in zip(out[3], out[1].tolist(), strict=True):
                info["original_reward"] = reward
                info["knn_reward"] = info["potential"] = 0.0
                info["shaping_step"] = info["pool_version"] = 0
                info["knn_active"] = False
            return out

    return RoundTripPerStep(venv)


def _a2c_model(
    stack: contextlib.ExitStack, backend: Backend | None, num_envs: int, zero_weights: bool
) -> tuple[Any, Any]:
    """An A2C model on ``num_envs`` CartPole-v1 envs shaped by ``backend`` (its session and
    task closed by ``stack``), and its env."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    import tamrm.sb3

    config = {"alpha": 0.0, "beta": 0.0} if zero_weights else {}
    bind = not isinstance(backend, NoValues)
    if isinstance(backend, NoValues):
        backend = backend.engine
    floor = backend if isinstance(backend, TcpFloor | WrapperFloor) else None
    session = None if floor else stack.enter_context(_shaped(backend, num_envs, **config))
    venv = make_vec_env("CartPole-v1", n_envs=num_envs, seed=0)
    if isinstance(floor, TcpFloor):
        env = _round_trip_per_step(venv, stack.enter_context(floor.round_trips(num_envs)))
    elif floor is not None:
        env = _round_trip_per_step(venv, None)
    else:
        env = venv if session is None else tamrm.sb3.ShapedVecEnv(venv, session)
    model = A2C("MlpPolicy", env, seed=0, device="cpu")
    if bind and isinstance(env, tamrm.sb3.ShapedVecEnv):
        env.bind_model(model)
    stack.callback(env.close)
    return model, env


def _fingerprint(model: Any) -> float:
    """The sum of the learned weights (equal sums: the runs learned the same)."""
    return float(sum(p.detach().double().sum() for p in model.policy.parameters()))


def a2c_run(
    backend: Backend | None, num_envs: int, timesteps: int, zero_weights: bool = False
) -> tuple[float, float]:
    """Seconds for an A2C ``learn(timesteps)`` on CartPole-v1, and a fingerprint of the
    learned weights (their sum).

    With ``zero_weights`` the task has alpha = beta = 0: every term is still computed and
    sent, but R_meta = R, so the learner sees the plain run's rewards and, seeded alike,
    learns exactly what the plain run learns (the fingerprints are equal). The time
    difference is then the cost of shaping alone; with the default weights it also holds
    the work of learning something else (other episode lengths, other resets)."""
    import torch

    torch.set_num_threads(1)
    with contextlib.ExitStack() as stack:
        model, _ = _a2c_model(stack, backend, num_envs, zero_weights)
        start = time.perf_counter()
        model.learn(total_timesteps=timesteps)
        elapsed = time.perf_counter() - start
        fingerprint = _fingerprint(model)
    return elapsed, fingerprint


def a2c_turns(
    backends: dict[str, Backend | None],
    num_envs: int,
    timesteps: int,
    zero_weights: bool,
    turn: int,
    rotation: int,
) -> dict[str, tuple[float, float, float]]:
    """Per variant of ``backends``: seconds, fingerprint and the seconds the learning
    thread spent off the CPU (its wall time less its CPU time: waiting for a server,
    or preempted) of an A2C ``learn(timesteps)`` run in turns, all in this process:
    every variant's model learns ``turn`` timesteps in its turn
    (``learn(turn, reset_num_timesteps=False)``), the order of the turns rotated by one
    each time (starting at ``rotation``). The machine's speed drifts by
    tens of percent over seconds here; turns of a few hundred milliseconds put every
    variant under the same drift, which interleaving whole runs does not. Each model keeps
    its own random state (torch, numpy, random) across turns, so it learns exactly what it
    learns alone (with alpha = beta = 0: the plain run's weights)."""
    import torch

    torch.set_num_threads(1)
    names = list(backends)
    with contextlib.ExitStack() as stack:
        models: dict[str, Any] = {}
        rng: dict[str, tuple[Any, Any, Any]] = {}
        for name in names:
            # A2C(seed=0) seeds every generator: take its state right after, as learn()
            # would find it.
            models[name], _ = _a2c_model(stack, backends[name], num_envs, zero_weights)
            rng[name] = (torch.get_rng_state(), np.random.get_state(), random.getstate())
        elapsed = dict.fromkeys(names, 0.0)
        off_cpu = dict.fromkeys(names, 0.0)
        for i in range(-(-timesteps // turn)):
            order = names[(rotation + i) % len(names) :] + names[: (rotation + i) % len(names)]
            for name in order:
                torch_state, np_state, py_state = rng[name]
                torch.set_rng_state(torch_state)
                np.random.set_state(np_state)
                random.setstate(py_state)
                steps = min(turn, timesteps - i * turn)
                start, cpu = time.perf_counter(), time.thread_time()
                models[name].learn(steps, reset_num_timesteps=False)
                wall = time.perf_counter() - start
                elapsed[name] += wall
                off_cpu[name] += wall - (time.thread_time() - cpu)
                rng[name] = (torch.get_rng_state(), np.random.get_state(), random.getstate())
        return {name: (elapsed[name], _fingerprint(models[name]), off_cpu[name]) for name in names}


def interleaved(
    variants: list[str], repeats: int, run: Callable[[str], float], what: str
) -> dict[str, list[float]]:
    """Samples per variant: one warm-up each, then ``repeats`` rounds, order rotated."""
    for name in variants:
        run(name)
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for r in range(repeats):
        order = variants[r % len(variants) :] + variants[: r % len(variants)]
        for name in order:
            secs = run(name)
            samples[name].append(secs)
            print(f"{what} repeat {r + 1} {name:10s} {secs:.3f} s", file=sys.stderr)
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="tamrm server address (default: start local ones)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1000, help="vector steps per loop run")
    parser.add_argument("--a2c-envs", type=int, default=8)
    parser.add_argument("--a2c-timesteps", type=int, default=20000)
    parser.add_argument("--no-sb3", action="store_true", help="skip the A2C runs")
    parser.add_argument(
        "--a2c-turn",
        type=int,
        default=400,
        help="A2C runs learn in turns of this many timesteps, every variant in one process "
        "(a2c_turns); 0: each learn() whole, in its own run, as older tables did",
    )
    parser.add_argument(
        "--a2c-weights",
        default="zero,default",
        help="A2C forms, comma-separated: zero (alpha = beta = 0: the plain run's learning, "
        "the cost of shaping alone) and/or default (the SPEC's weights)",
    )
    parser.add_argument("--no-loop", action="store_true", help="skip the vector-loop runs")
    parser.add_argument(
        "--value-fn", action="store_true", help="also time the loop with a linear value_fn"
    )
    parser.add_argument(
        "--variants",
        help=f"comma-separated subset of {','.join(VARIANTS)} (plain is always run)",
    )
    parser.add_argument(
        "--far-ms",
        type=float,
        default=1.0,
        help="the *-far variants: delay of each direction between learner and server (ms)",
    )
    parser.add_argument("--quick", action="store_true", help="small sizes, 2 repeats")
    ns = parser.parse_args()
    far = f"{ns.far_ms:g} ms each way"
    labels = {name: label.format(far=far) for name, label in LABELS.items()}
    if ns.quick:
        ns.repeats, ns.steps, ns.a2c_timesteps, ns.a2c_weights = 2, 300, 4000, "zero"
    variants = list(VARIANTS) if not ns.variants else ["plain", *ns.variants.split(",")]
    variants = list(dict.fromkeys(v for v in variants if v))
    if ns.server:
        variants = [v for v in variants if not v.startswith("remote")] + ["server"]

    load = [os.getloadavg()]
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with contextlib.ExitStack() as stack:
        backends: dict[str, Backend | None] = {"plain": None}
        tmp = stack.enter_context(tempfile.TemporaryDirectory())
        for name in variants:
            if name == "engine":
                backends[name] = stack.enter_context(tamrm.Engine())
            elif name == "engine-novalues":
                backends[name] = NoValues(stack.enter_context(tamrm.Engine()))
            elif name == "wrapper-floor":
                backends[name] = WrapperFloor()
            elif name == "engine-dir":
                backends[name] = stack.enter_context(tamrm.Engine(os.path.join(tmp, "engine")))
            elif name == "remote":
                server = stack.enter_context(tamrm.local_server(in_memory=True))
                backends[name] = stack.enter_context(tamrm.Client(server.address))
            elif name in ("remote-poll", "remote-poll-1t"):
                args = ["--worker-threads", "1"] if name == "remote-poll-1t" else []
                server = stack.enter_context(tamrm.local_server(in_memory=True, args=args))
                client = tamrm.Client(server.address, busy_poll_us=BUSY_POLL_US)
                backends[name] = stack.enter_context(client)
            elif name == "remote-dir":
                server = stack.enter_context(tamrm.local_server())
                backends[name] = stack.enter_context(tamrm.Client(server.address))
            elif name in ("local", "local-dir", "local-far"):
                metrics = f"127.0.0.1:{_free_port()}"
                server = stack.enter_context(
                    tamrm.local_server(
                        in_memory=name == "local", args=["--metrics-listen", metrics]
                    )
                )
                address = server.address
                if name == "local-far":
                    address = stack.enter_context(slow_path(address, ns.far_ms))
                client = stack.enter_context(tamrm.Client(address))
                backends[name] = Local(client, metrics)
            elif name == "remote-far":
                server = stack.enter_context(tamrm.local_server())
                address = stack.enter_context(slow_path(server.address, ns.far_ms))
                backends[name] = stack.enter_context(tamrm.Client(address))
            elif name == "server":
                backends[name] = stack.enter_context(tamrm.Client(ns.server))
            elif name == "tcp-floor":
                floor = TcpFloor(tmp)
                stack.callback(floor.close)
                backends[name] = floor
            elif name != "plain":
                parser.error(f"unknown variant {name!r}")

        # (workload, vector steps per run, variant -> samples)
        tables: list[tuple[str, int, dict[str, list[float]], int]] = []
        off_cpu: list[str] = []
        n, steps = ns.num_envs, ns.steps
        if not ns.no_loop:
            for with_values in (False, True) if ns.value_fn else (False,):
                loop = f"{n}-env CartPole-v1 loop, {steps} vector steps"
                loop += " + value_fn" if with_values else ""
                samples = interleaved(
                    variants,
                    ns.repeats,
                    lambda v, w=with_values: vector_loop(backends[v], n, steps, w),  # type: ignore[misc]
                    "loop",
                )
                tables.append((loop, steps, samples, n * steps))
                load.append(os.getloadavg())
        if not ns.no_sb3:
            k, ts = ns.a2c_envs, ns.a2c_timesteps
            for form in ns.a2c_weights.split(","):
                if form not in ("zero", "default"):
                    parser.error(f"--a2c-weights: unknown form {form!r}")
                zero = form == "zero"
                prints: dict[str, set[float]] = {}

                def run(v: str, zero: bool = zero, prints: dict[str, set[float]] = prints) -> float:
                    secs, fingerprint = a2c_run(backends[v], k, ts, zero)
                    prints.setdefault(v, set()).add(fingerprint)
                    return secs

                if ns.a2c_turn > 0:
                    samples = {name: [] for name in variants}
                    waited: dict[str, list[float]] = {name: [] for name in variants}
                    for r in range(-1, ns.repeats):  # round -1: the warm-up
                        timed = a2c_turns(
                            {v: backends[v] for v in variants}, k, ts, zero, ns.a2c_turn, r
                        )
                        for name, (secs, fingerprint, off) in timed.items():
                            prints.setdefault(name, set()).add(fingerprint)
                            if r >= 0:
                                samples[name].append(secs)
                                waited[name].append(off)
                        print(f"a2c {form} round {r + 1}: {timed}", file=sys.stderr)
                else:
                    samples = interleaved(variants, ns.repeats, run, f"a2c {form}")
                label = (
                    f"SB3 A2C learn({ts}), {k} envs, "
                    + (f"in turns of {ns.a2c_turn}, " if ns.a2c_turn > 0 else "")
                    + ("alpha = beta = 0 (same learning)" if zero else "default weights")
                )
                if zero and any(p != prints["plain"] for p in prints.values()):
                    # The premise of the form: say so loudly if it does not hold.
                    print(f"warning: {label}: the runs learned differently: {prints}")
                    label += " (learning DIFFERED)"
                tables.append((label, ts // k, samples, ts))
                load.append(os.getloadavg())
                if ns.a2c_turn > 0:
                    off_cpu.append(
                        f"{label}: the learning thread off the CPU (wall less CPU time), "
                        "median ms per run: "
                        + ", ".join(
                            f"{labels[v]} {statistics.median(waited[v]) * 1e3:.0f}"
                            for v in variants
                        )
                    )

        # Read while the servers run: messages they received per env step.
        messages = []
        for name in variants:
            backend = backends.get(name)
            if isinstance(backend, Local) and STEPS_SHAPED.get(backend):
                received = backend.messages_received()
                steps = STEPS_SHAPED[backend]
                messages.append(
                    f"{labels[name]}: the server received {received:,.0f} Follow messages "
                    f"for {steps:,} env steps: 1/{steps / max(received, 1):,.0f} per env step"
                )

    print(
        f"\n{started}; {platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; {ns.repeats} interleaved repeats after 1 warm-up; "
        f"load average (1 min) {min(x[0] for x in load):.1f}-{max(x[0] for x in load):.1f}\n"
    )
    for line in messages + off_cpu:
        print(line)
    print(
        "| workload | variant | median time (s) | env steps/s | overhead (median of "
        "per-repeat ratios) | per vector step |"
    )
    print("|---|---|---:|---:|---:|---:|")
    for workload, vector_steps, samples, env_steps in tables:
        base = samples["plain"]
        base_med = statistics.median(base)
        for name in variants:
            runs = samples[name]
            med = statistics.median(runs)
            if name == "plain":
                over = per_step = "—"
            else:
                ratio = statistics.median(s / b - 1 for s, b in zip(runs, base, strict=True))
                over = f"{ratio * 100:+.1f}%"
                per_step = f"{(med - base_med) / vector_steps * 1e6:+.0f} µs"
            print(
                f"| {workload} | {labels[name]} | {med:.3f} | {env_steps / med:,.0f} "
                f"| {over} | {per_step} |"
            )


if __name__ == "__main__":
    main()
