"""Types of the native extension (``clients/python/native``, built by maturin)."""

from pathlib import Path

import numpy as np
import numpy.typing as npt

class StatusError(Exception):
    """A failed call: ``args == (code: int, message: str)``, the gRPC status."""

# (parts: (3, B) rows R_meta, r(t), F; steps; knn_active; pool version)
_Answer = tuple[
    npt.NDArray[np.float64],
    npt.NDArray[np.int64],
    npt.NDArray[np.bool_],
    int,
]

class NativeStream:
    @property
    def opened(self) -> bytes: ...
    @property
    def closed(self) -> bool: ...
    def step(
        self,
        env_ids: npt.NDArray[np.int64] | None,
        actions: npt.NDArray[np.generic],
        rewards: npt.NDArray[np.float64],
        terminated: npt.NDArray[np.bool_] | None,
        truncated: npt.NDArray[np.bool_] | None,
        values: npt.NDArray[np.floating] | None,
        next_values: npt.NDArray[np.floating] | None,
        q_values: npt.NDArray[np.floating] | None,
        next_q_values: npt.NDArray[np.floating] | None,
        score_rows: npt.NDArray[np.int64] | None,
        score_values: npt.NDArray[np.float64] | None,
    ) -> _Answer: ...
    @property
    def pool_version(self) -> int: ...
    def abandon(self, envs: list[int]) -> None: ...
    def episode_steps(self) -> npt.NDArray[np.int64]: ...
    def close(self) -> None: ...
    def reopen(self) -> None: ...

class Mlp:
    def __init__(
        self, layers: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], str]]
    ) -> None: ...
    @property
    def inputs(self) -> int: ...
    def __call__(self, obs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]: ...

class VecStep:
    def __init__(
        self,
        stream: NativeStream,
        value_fn_type: type,
        action_dim: int,
        alpha: float,
        beta: float,
    ) -> None: ...
    @property
    def steps(self) -> int: ...
    @property
    def critic_rows(self) -> int: ...
    def step(
        self,
        env: object,
        actions: object,
        obs: object,
        rewards: object,
        dones: object,
        infos: object,
    ) -> npt.NDArray[np.float32] | None: ...

def record_step(
    env: object,
    infos: object,
    dones: object,
    env_rewards: object,
    result: object,
    alpha: float,
    beta: float,
) -> None: ...

class Engine:
    def __init__(self, data_dir: str | Path | None = None) -> None: ...
    def call(self, method: str, request: bytes) -> bytes: ...
    def open(self, task_id: str, num_envs: int, client_id: str) -> NativeStream: ...
    def flush(self) -> None: ...
    @property
    def description(self) -> str: ...

MAX_BUSY_POLL_US: int
__version__: str

class ChannelOptions:
    def __init__(
        self,
        *,
        metadata: list[tuple[str, str]] = ...,
        tls: bool = False,
        root_certificates: bytes | None = None,
        certificate_chain: bytes | None = None,
        private_key: bytes | None = None,
        server_name: str | None = None,
        keepalive_secs: float | None = 30.0,
        keepalive_timeout_secs: float = 20.0,
        resume_timeout_secs: float | None = 60.0,
        busy_poll_us: int = 0,
    ) -> None: ...
    @property
    def tls(self) -> bool: ...

class Channel:
    def __init__(self, targets: list[str], options: ChannelOptions | None = None) -> None: ...
    @property
    def tls(self) -> bool: ...
    def call(self, method: str, request: bytes, timeout: float | None = None) -> bytes: ...
    def wait_ready(self, timeout: float) -> None: ...
    def health(self, service: str, timeout: float) -> bool: ...
    def open(self, task_id: str, num_envs: int, client_id: str) -> NativeStream: ...
    def follow(self, task_id: str, num_envs: int, client_id: str) -> NativeStream: ...
