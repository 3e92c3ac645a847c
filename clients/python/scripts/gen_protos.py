#!/usr/bin/env python3
"""Regenerate the gRPC stubs of the tamrm Python client from ``proto/``.

The repository's ``proto/`` directory is the single source of the API. This script runs
the pinned ``grpcio-tools`` (its bundled ``protoc``) with the pinned ``mypy-protobuf``
plugins and writes::

    clients/python/src/tamrm/_proto/__init__.py
    clients/python/src/tamrm/_proto/tamrm/__init__.py
    clients/python/src/tamrm/_proto/tamrm/v1/__init__.py
    clients/python/src/tamrm/_proto/tamrm/v1/shaping_pb2.py      (+ .pyi)
    clients/python/src/tamrm/_proto/tamrm/v1/shaping_pb2_grpc.py (+ .pyi)

The generators emit absolute imports (``from tamrm.v1 import shaping_pb2``) that would
resolve against the client package itself (it is also called ``tamrm``), so they are
rewritten to ``from tamrm._proto.tamrm.v1 import shaping_pb2``. The proto file's
descriptor keeps its name ``tamrm/v1/shaping.proto``.

Usage::

    python clients/python/scripts/gen_protos.py            # regenerate in place
    python clients/python/scripts/gen_protos.py --check    # exit 1 if the stubs are stale
    python clients/python/scripts/gen_protos.py --out DIR  # generate somewhere else

Requires the ``dev`` extra (``grpcio-tools==1.85.1``, ``mypy-protobuf==5.1.0``).
"""

from __future__ import annotations

import argparse
import filecmp
import os
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CLIENT_DIR = HERE.parent
REPO_ROOT = CLIENT_DIR.parent.parent
PROTO_ROOT = REPO_ROOT / "proto"
DEFAULT_OUT = CLIENT_DIR / "src" / "tamrm" / "_proto"
PROTO_FILES = ["tamrm/v1/shaping.proto"]

PINNED = {"grpcio-tools": "1.85.1", "mypy-protobuf": "5.1.0"}

INIT_DOCS = {
    Path("__init__.py"): '"""Generated gRPC stubs of the tamrm API (scripts/gen_protos.py)."""\n',
    Path("tamrm/__init__.py"): '"""Generated: proto package ``tamrm``."""\n',
    Path("tamrm/v1/__init__.py"): '"""Generated: proto package ``tamrm.v1``."""\n',
}

IMPORT_REWRITES = [
    ("from tamrm.v1 import ", "from tamrm._proto.tamrm.v1 import "),
    ("import tamrm.v1.", "import tamrm._proto.tamrm.v1."),
]


def _check_pins() -> None:
    from importlib.metadata import version

    for dist, want in PINNED.items():
        have = version(dist)
        if have != want:
            raise SystemExit(
                f"gen_protos: {dist}=={have} is installed but {want} is pinned; "
                "install the client's dev extra: pip install -e 'clients/python[dev]'"
            )


def _plugin(name: str) -> str:
    candidate = Path(sys.executable).parent / name
    if candidate.exists():
        return str(candidate)
    found = shutil.which(name)
    if found is None:
        raise SystemExit(f"gen_protos: plugin {name} not found (is mypy-protobuf installed?)")
    return found


def generate(out: Path) -> None:
    """Generate the stubs into ``out`` (created if missing, previous contents replaced)."""
    from grpc_tools import protoc

    _check_pins()
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"--python_out={out}",
        f"--grpc_python_out={out}",
        f"--mypy_out={out}",
        f"--mypy_grpc_out={out}",
        f"--plugin=protoc-gen-mypy={_plugin('protoc-gen-mypy')}",
        f"--plugin=protoc-gen-mypy_grpc={_plugin('protoc-gen-mypy_grpc')}",
        *PROTO_FILES,
    ]
    cwd = os.getcwd()
    try:
        # protoc records the proto path relative to -I, so the cwd does not matter, but
        # mypy-protobuf prints "Writing ..." lines relative to it: keep it stable.
        os.chdir(out)
        rc = protoc.main(args)
    finally:
        os.chdir(cwd)
    if rc != 0:
        raise SystemExit(f"gen_protos: protoc failed with exit code {rc}")
    for path in sorted(out.rglob("*")):
        if path.suffix not in (".py", ".pyi"):
            continue
        text = path.read_text(encoding="utf-8")
        for old, new in IMPORT_REWRITES:
            text = text.replace(old, new)
        path.write_text(text, encoding="utf-8")
    for rel, doc in INIT_DOCS.items():
        (out / rel).write_text(doc, encoding="utf-8")


def stale_files(expected: Path, actual: Path) -> list[str]:
    """Return the relative paths that differ between two generated trees."""

    def files(root: Path) -> set[str]:
        return {
            str(p.relative_to(root))
            for p in root.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts
        }

    want, have = files(expected), files(actual)
    diff = sorted(want ^ have)
    for rel in sorted(want & have):
        if not filecmp.cmp(expected / rel, actual / rel, shallow=False):
            diff.append(rel)
    return diff


def main() -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    parser.add_argument(
        "--check", action="store_true", help="compare with the output directory instead"
    )
    ns = parser.parse_args()
    if ns.check:
        with tempfile.TemporaryDirectory() as tmp:
            fresh = Path(tmp) / "_proto"
            generate(fresh)
            diff = stale_files(fresh, ns.out)
        if diff:
            print("stale generated stubs (run scripts/gen_protos.py):", *diff, sep="\n  ")
            return 1
        print("generated stubs are up to date")
        return 0
    generate(ns.out)
    print(f"wrote stubs to {ns.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
