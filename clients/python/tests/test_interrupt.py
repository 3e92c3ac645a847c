"""Ctrl-C while the server hangs: no 10 s wait, no chained traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

import tamrm

SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, threading, time
    import tamrm

    # Ctrl-C as in a terminal, even when the tests run from a shell's background job, whose
    # children start with SIGINT ignored (then Python installs no KeyboardInterrupt).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    address, pid, where = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    client = tamrm.Client(address)
    client.create_task("t", num_actions=2)
    with client.session("t") as session:
        session.step([1], [1.0])
        os.kill(pid, signal.SIGSTOP)  # the server hangs from now on
        # ... once every thread of it has stopped (a loaded machine takes a while; a fast
        # client could otherwise still get its answer from a thread not yet stopped).
        tasks = f"/proc/{pid}/task"
        while any(
            open(f"{tasks}/{t}/stat").read().rsplit(")", 1)[1].split()[0] not in "tT"
            for t in os.listdir(tasks)
        ):
            time.sleep(0.001)
        threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()  # Ctrl-C
        print("start", time.monotonic(), flush=True)
        if where == "step":
            session.step([1], [1.0])  # blocks: the server never answers
        else:
            time.sleep(30)  # the user's own code, with a batch unanswered
    """
)


@pytest.mark.parametrize("where", ["step", "user-code"])
def test_interrupt_while_the_server_hangs(server_binary: str, where: str) -> None:
    with tamrm.local_server(binary=server_binary, in_memory=True) as srv:
        try:
            proc = subprocess.run(
                [sys.executable, "-c", SCRIPT, srv.address, str(srv.process.pid), where],
                capture_output=True,
                text=True,
                timeout=60,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
            ended = time.monotonic()  # the same system-wide clock as the child's
        finally:
            os.kill(srv.process.pid, signal.SIGCONT)
    assert proc.returncode != 0
    # Ctrl-C came 0.5 s after "start"; unwinding must not wait for the hung server (10 s).
    assert ended - float(proc.stdout.split()[1]) < 3.0, proc.stderr
    err = proc.stderr
    assert err.count("Traceback") == 1, err
    assert "During handling of the above exception" not in err, err
    assert "direct cause" not in err, err
    assert err.rstrip().splitlines()[-1] == "KeyboardInterrupt", err
