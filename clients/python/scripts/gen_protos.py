#!/usr/bin/env python3
"""Regenerate the protobuf stubs of the tamrm Python client from ``proto/``.

The repository's ``proto/`` directory is the single source of the API. This script runs
the pinned ``grpcio-tools`` (its bundled ``protoc``) with the pinned ``mypy-protobuf``
plugins and writes the messages, which the package uses at runtime::

    clients/python/src/tamrm/_proto/__init__.py
    clients/python/src/tamrm/_proto/tamrm/__init__.py
    clients/python/src/tamrm/_proto/tamrm/v1/__init__.py
    clients/python/src/tamrm/_proto/tamrm/v1/shaping_pb2.py      (+ .pyi)

and grpcio's service stubs, which only the tests use (their grpcio stand-in for an old
server; every transport of the package is native), beside the tests::

    clients/python/tests/grpc_stubs/__init__.py
    clients/python/tests/grpc_stubs/shaping_pb2_grpc.py          (+ .pyi)

The generators emit absolute imports (``from tamrm.v1 import shaping_pb2``) that would
resolve against the client package itself (it is also called ``tamrm``), so they are
rewritten to ``from tamrm._proto.tamrm.v1 import shaping_pb2``. The proto file's
descriptor keeps its name ``tamrm/v1/shaping.proto``.

Usage::

    python clients/python/scripts/gen_protos.py            # regenerate in place
    python clients/python/scripts/gen_protos.py --check    # exit 1 if the stubs are stale
    python clients/python/scripts/gen_protos.py --out DIR --grpc-out DIR2  # somewhere else

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
DEFAULT_GRPC_OUT = CLIENT_DIR / "tests" / "grpc_stubs"
PROTO_FILES = ["tamrm/v1/shaping.proto"]

PINNED = {"grpcio-tools": "1.85.1", "mypy-protobuf": "5.1.0"}

INIT_DOCS = {
    Path("__init__.py"): '"""Generated protobuf messages of tamrm (scripts/gen_protos.py)."""\n',
    Path("tamrm/__init__.py"): '"""Generated: proto package ``tamrm``."""\n',
    Path("tamrm/v1/__init__.py"): '"""Generated: proto package ``tamrm.v1``."""\n',
}
GRPC_INIT_DOC = (
    '"""Generated grpcio service stubs of the tamrm API, for the tests only '
    '(scripts/gen_protos.py)."""\n'
)
#: The generated files' name endings that go to the tests (grpcio's service stubs).
GRPC_SUFFIXES = ("_pb2_grpc.py", "_pb2_grpc.pyi")

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


def generate(out: Path, grpc_out: Path) -> None:
    """Generate the messages into ``out`` and the service stubs into ``grpc_out``.

    Both directories are created if missing; their previous contents are replaced.
    """
    _check_pins()
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp)
        _protoc(raw)
        for target in (out, grpc_out):
            if target.exists():
                shutil.rmtree(target)
            target.mkdir(parents=True)
        for path in sorted(raw.rglob("*")):
            if path.suffix not in (".py", ".pyi"):
                continue
            rel = path.relative_to(raw)
            dest = grpc_out / rel.name if path.name.endswith(GRPC_SUFFIXES) else out / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, dest)
    for rel, doc in INIT_DOCS.items():
        (out / rel).write_text(doc, encoding="utf-8")
    (grpc_out / "__init__.py").write_text(GRPC_INIT_DOC, encoding="utf-8")


def _protoc(out: Path) -> None:
    """Run protoc and its plugins into ``out``, with the imports rewritten."""
    from grpc_tools import protoc

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
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="output directory of the messages"
    )
    parser.add_argument(
        "--grpc-out",
        type=Path,
        default=DEFAULT_GRPC_OUT,
        help="output directory of the tests' grpcio service stubs",
    )
    parser.add_argument(
        "--check", action="store_true", help="compare with the output directory instead"
    )
    ns = parser.parse_args()
    if ns.check:
        with tempfile.TemporaryDirectory() as tmp:
            fresh, fresh_grpc = Path(tmp) / "_proto", Path(tmp) / "grpc_stubs"
            generate(fresh, fresh_grpc)
            diff = [str(ns.out / rel) for rel in stale_files(fresh, ns.out)]
            diff += [str(ns.grpc_out / rel) for rel in stale_files(fresh_grpc, ns.grpc_out)]
        if diff:
            print("stale generated stubs (run scripts/gen_protos.py):", *diff, sep="\n  ")
            return 1
        print("generated stubs are up to date")
        return 0
    generate(ns.out, ns.grpc_out)
    print(f"wrote stubs to {ns.out} and {ns.grpc_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
