#!/usr/bin/env python3
"""What the wheel costs and saves, side by side in one run.

1. **Size**: the wheel's bytes against the compiled extension (``tamrm/_native.abi3.so``
   of a source install, as pip builds it) plus the server binary stripped. Target: at
   most 1.5.
2. **Install time**: ``pip install`` into a fresh venv from one local wheelhouse (the
   wheel and every dependency as wheels, ``--no-index``): the wheel, against the sdist
   (maturin compiles the extension with a cold ``CARGO_TARGET_DIR``, crates from the
   local cargo cache, as a user's first source install does; that it builds at all is
   the proof that the sdist holds what a build needs). Target: the wheel takes at most
   10 % of the source install.
3. **Speed of the server in the wheel**: ``benchmarks/step_latency.py``'s native client
   (16 envs) against the wheel's server and against ``target/release/tamrm``, rounds
   interleaved; the median over rounds of the per-round p50 ratio. Target: within 10 %.

::

    python benchmarks/wheel_cost.py --wheel dist/tamrm-*.whl --sdist dist/tamrm-*.tar.gz
    python benchmarks/wheel_cost.py --wheel dist/tamrm-*.whl   # no compile
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]


def stripped_size(binary: Path, tmp: Path) -> int:
    copy = tmp / "stripped"
    copy.write_bytes(binary.read_bytes())
    subprocess.run(["strip", str(copy)], check=True)
    return copy.stat().st_size


def sizes(wheel: Path, tmp: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        server = next(i for i in z.infolist() if i.filename.endswith(".data/scripts/tamrm"))
        ext = next(i for i in z.infolist() if i.filename.endswith("_native.abi3.so"))
        print(f"- in the wheel: extension {ext.file_size} B, server {server.file_size} B")
    source_ext = REPO / "clients/python/src/tamrm/_native.abi3.so"
    binary = REPO / "target/release/tamrm"
    if not source_ext.exists() or not binary.exists():
        print("- size ratio: skipped (needs a source install's extension and target/release)")
        return
    floor = source_ext.stat().st_size + stripped_size(binary, tmp)
    whl = wheel.stat().st_size
    print(
        f"- wheel {whl / 1e6:.1f} MB; source extension {source_ext.stat().st_size / 1e6:.1f} MB"
        f" + server stripped: {floor / 1e6:.1f} MB; ratio {whl / floor:.2f} (target <= 1.5)"
    )


def timed_install(target: str, house: Path, tmp: Path, name: str, env: dict[str, str]) -> float:
    venv = tmp / name
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    t0 = time.perf_counter()
    subprocess.run(
        [str(venv / "bin/pip"), "install", "-q", "--no-index", "--find-links", str(house), target],
        check=True,
        env=env,
    )
    return time.perf_counter() - t0


def requirements(wheel: Path) -> list[str]:
    """The wheel's own dependencies without extras (its METADATA's Requires-Dist)."""
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode().splitlines()
    found = [line.split(":", 1)[1].strip() for line in lines if line.startswith("Requires-Dist:")]
    return [r for r in found if "extra ==" not in r]


def install_times(wheel: Path, sdist: Path | None, tmp: Path) -> None:
    house = tmp / "wheelhouse"
    pip = [sys.executable, "-m", "pip", "download", "-q", "-d", str(house)]
    subprocess.run([*pip, *requirements(wheel), "maturin>=1.9,<2"], check=True)
    env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    t_wheel = timed_install(str(wheel), house, tmp, "from-wheel", env)
    print(f"- install from the wheel: {t_wheel:.1f} s")
    if sdist is None:
        return
    cold = {**env, "CARGO_TARGET_DIR": str(tmp / "cold-target"), "CARGO_NET_OFFLINE": "true"}
    t_source = timed_install(str(sdist), house, tmp, "from-source", cold)
    print(
        f"- install from source: {t_source:.1f} s; wheel / source "
        f"{t_wheel / t_source:.3f} (target <= 0.10)"
    )


def server_speed(wheel_server: Path, rounds: int, steps: int) -> None:
    sys.path.insert(0, str(HERE))
    import step_latency  # the same client, task and seeding as the step-latency table

    import tamrm

    binaries = {"cargo": REPO / "target/release/tamrm", "wheel": wheel_server}
    ns = argparse.Namespace(task=step_latency.TASK, steps=steps, warmup=200)
    p50: dict[str, list[float]] = {k: [] for k in binaries}
    for r in range(rounds):
        order = list(binaries) if r % 2 == 0 else list(reversed(binaries))
        for name in order:
            with tamrm.local_server(binary=binaries[name], in_memory=True) as srv:
                with tamrm.Client(srv.address) as admin:
                    admin.create_task(ns.task, **step_latency.task_config())
                    step_latency.seed_pool(admin, ns.task)
                res = step_latency.run_client("native", 16, ns, srv.address, None, None)
            assert res is not None, f"the client failed against the {name} server"
            p50[name].append(res["p50_us"])
            print(f"  round {r + 1} {name}: p50 {res['p50_us']:.1f} µs", file=sys.stderr)
    ratio = statistics.median(w / c for w, c in zip(p50["wheel"], p50["cargo"], strict=True))
    print(
        f"- step p50 (native client, 16 envs, {rounds} rounds): cargo "
        f"{statistics.median(p50['cargo']):.1f} µs, wheel {statistics.median(p50['wheel']):.1f}"
        f" µs; wheel / cargo {ratio:.3f} (target within 10 %)"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--wheel", type=Path, required=True)
    p.add_argument("--sdist", type=Path, help="also install from this sdist (a cold compile)")
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--steps", type=int, default=3000)
    ns = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} CPUs")
        sizes(ns.wheel, tmp)
        install_times(ns.wheel, ns.sdist, tmp)
        with zipfile.ZipFile(ns.wheel) as z:
            name = next(n for n in z.namelist() if n.endswith(".data/scripts/tamrm"))
            server = tmp / "wheel-server"
            server.write_bytes(z.read(name))
            server.chmod(0o755)
        server_speed(server, ns.rounds, ns.steps)


if __name__ == "__main__":
    main()
