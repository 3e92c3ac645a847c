"""A remote session's own connection: it stays alive while the caller does not step.

Each session's stream runs on a connection of its own, driven by the thread that calls
``step`` (no hand-off to a worker thread). Between steps a keeper thread answers the
server's keepalive pings; without it, a training loop that pauses (evaluation, saving)
for longer than the server's keepalive interval plus timeout would lose its stream.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from streams import in_threads

import tamrm
import tamrm.aio


def test_a_session_survives_a_pause_longer_than_the_keepalive_timeout(
    server_binary: str,
) -> None:
    # The server pings every second and closes a connection that has not answered a
    # ping within a second; the session sleeps 4 s between two steps, with resuming off,
    # so a closed connection would fail the second step.
    args = ["--keepalive-secs", "1", "--keepalive-timeout-secs", "1"]
    with (
        tamrm.local_server(binary=server_binary, in_memory=True, args=args) as server,
        tamrm.Client(server.address, keepalive_secs=None, resume_timeout_secs=None) as client,
    ):
        client.create_task("pause", num_actions=2)
        with client.session("pause", 2) as session:
            first = session.step([0, 1], [1.0, 1.0])
            time.sleep(4.0)
            second = session.step([1, 1], [1.0, 1.0])
            np.testing.assert_array_equal(second.steps, first.steps + 1)
            assert not session.closed
        assert client.get_task("pause").stats.steps_shaped == 4


def test_sessions_in_threads_have_their_own_connections(server: tamrm.LocalServer) -> None:
    # Several threads, one session each, stepping at once on one client: every answer
    # is its own session's (the step index of each env counts that session's steps).
    with tamrm.Client(server.address) as client:
        client.create_task("threads-own-connections", num_actions=3)

        def run(seed: int) -> None:
            rng = np.random.default_rng(seed)
            with client.session("threads-own-connections", 4) as session:
                for t in range(300):
                    result = session.step(rng.integers(0, 3, size=4), np.ones(4))
                    assert (result.steps == t).all(), (seed, t, result.steps)

        in_threads(run, 4)
        assert client.get_task("threads-own-connections").stats.steps_shaped == 4 * 300 * 4


def _run_steps(client: tamrm.Client, task_id: str, seed: int) -> list[np.ndarray]:
    """One session of random steps (episode ends, values) on a fresh task; the answers."""
    client.create_task(task_id, num_actions=3, pool_capacity=4, k=2, start_step=2, min_pool_size=2)
    rng = np.random.default_rng(seed)
    out = []
    with client.session(task_id, 3) as session:
        for _ in range(200):
            ends = rng.random(3) < 0.1
            result = session.step(
                rng.integers(0, 3, size=3),
                rng.normal(size=3),
                terminated=ends,
                values=rng.normal(size=3),
                next_values=rng.normal(size=3),
            )
            out += [result.rewards, result.knn_rewards, result.potentials, result.steps]
    return out


@pytest.mark.parametrize("busy_poll_us", [1, 500, 1_000_000])
def test_busy_polling_gives_the_answers_of_a_sleeping_wait(
    server: tamrm.LocalServer, busy_poll_us: int
) -> None:
    # 1 µs: nearly every answer comes after the poll, through the sleeping wait;
    # 500 µs and 1 s: nearly every answer is found by polling. Either way the same
    # answers, bit for bit, as without polling.
    with (
        tamrm.Client(server.address) as plain,
        tamrm.Client(server.address, busy_poll_us=busy_poll_us) as polling,
    ):
        tag = f"busy-poll-{busy_poll_us}"
        expected = _run_steps(plain, f"{tag}-off", seed=busy_poll_us)
        got = _run_steps(polling, f"{tag}-on", seed=busy_poll_us)
        assert len(got) == len(expected)
        assert any(np.any(knn != 0) for knn in expected[1::4])  # the kNN term was on
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("value", "error", "match"),
    [
        (-1, ValueError, "from 0 \\(off\\) to 1000000"),
        (1_000_001, ValueError, "got 1000001"),
        (1.5, TypeError, "must be an int"),
        (True, TypeError, "must be an int"),
        ("100", TypeError, "must be an int"),
    ],
)
def test_busy_poll_us_is_checked(value: object, error: type[Exception], match: str) -> None:
    with pytest.raises(error, match=match):
        tamrm.Client("127.0.0.1:1", busy_poll_us=value)  # type: ignore[arg-type]
    with pytest.raises(error, match=match):
        tamrm.aio.Client("127.0.0.1:1", busy_poll_us=value)  # type: ignore[arg-type]
