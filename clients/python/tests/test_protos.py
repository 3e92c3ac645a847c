"""The checked-in stubs are exactly what the pinned generators make from proto/: the
messages in the package, grpcio's service stubs beside the tests (their only user)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

CLIENT = Path(__file__).resolve().parents[1]
CHECKED_IN = CLIENT / "src" / "tamrm" / "_proto"
CHECKED_IN_GRPC = CLIENT / "tests" / "grpc_stubs"


def _load_gen_protos():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(
        "gen_protos", CLIENT / "scripts" / "gen_protos.py"
    )
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_stubs_are_up_to_date(tmp_path: Path) -> None:
    pytest.importorskip("grpc_tools")
    gen = _load_gen_protos()
    fresh, fresh_grpc = tmp_path / "_proto", tmp_path / "grpc_stubs"
    gen.generate(fresh, fresh_grpc)
    stale = gen.stale_files(fresh, CHECKED_IN) + gen.stale_files(fresh_grpc, CHECKED_IN_GRPC)
    assert stale == [], f"stale stubs, run scripts/gen_protos.py: {stale}"
    # The comparison itself detects a change.
    target = fresh / "tamrm" / "v1" / "shaping_pb2.py"
    target.write_bytes(target.read_bytes() + b"\n")
    assert gen.stale_files(fresh, CHECKED_IN) == ["tamrm/v1/shaping_pb2.py"]
    (fresh_grpc / "shaping_pb2_grpc.pyi").unlink()
    assert gen.stale_files(fresh_grpc, CHECKED_IN_GRPC) == ["shaping_pb2_grpc.pyi"]


def test_check_mode_exit_code() -> None:
    pytest.importorskip("grpc_tools")
    proc = subprocess.run(
        [sys.executable, str(CLIENT / "scripts" / "gen_protos.py"), "--check"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_stubs_import_inside_the_package() -> None:
    from grpc_stubs import shaping_pb2_grpc

    from tamrm._proto.tamrm.v1 import shaping_pb2

    assert shaping_pb2_grpc.tamrm_dot_v1_dot_shaping__pb2 is shaping_pb2
    assert shaping_pb2.DESCRIPTOR.name == "tamrm/v1/shaping.proto"
    assert shaping_pb2.DESCRIPTOR.package == "tamrm.v1"
    assert hasattr(shaping_pb2_grpc, "ShapingStub")
    service = shaping_pb2.DESCRIPTOR.services_by_name["Shaping"]
    assert [m.name for m in service.methods] == [
        "CreateTask",
        "GetTask",
        "ListTasks",
        "DeleteTask",
        "ResetPool",
        "GetPool",
        "AddTrajectory",
        "Shape",
        "Follow",
    ]
    # The stubs did not shadow or get shadowed by the client package.
    assert "tamrm.v1" not in sys.modules
    # The package ships the messages only: grpcio's stubs are the tests'.
    assert not list(CHECKED_IN.rglob("*_grpc.py*"))


def test_the_package_runs_without_grpcio() -> None:
    # Every transport is native: importing the package and its submodules, and a call,
    # loads no grpcio (a dev dependency only, for the tests' stand-in old server).
    import subprocess
    import sys

    code = (
        "import sys, tamrm, tamrm.aio, tamrm.gym\n"
        "e = tamrm.Engine(); e.create_task('t', num_actions=2)\n"
        "assert tamrm._server.health_check('127.0.0.1:9', timeout=0.1) is False\n"
        "bad = [m for m in sys.modules if m.startswith('grpc')]\n"
        "assert not bad, bad\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
