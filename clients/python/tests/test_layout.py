"""The Python client's layout rules, read off its sources (as ``tests/layers.rs`` does for
the Rust crates; docs/architecture.md, "The Python client"): one module owns the native
extension, and the extension's stub describes what it is built with."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

CLIENT = Path(__file__).resolve().parents[1]
PACKAGE = CLIENT / "src" / "tamrm"
#: The one module that imports the native extension.
BRIDGE = PACKAGE / "_bridge.py"
EXTENSION = "tamrm._native"


def sources() -> list[Path]:
    """Every Python source file of the package."""
    return sorted(PACKAGE.rglob("*.py"))


def rel(path: Path) -> str:
    return str(path.relative_to(CLIENT))


def imports_the_extension(tree: ast.AST) -> list[int]:
    """The lines of ``tree`` that import ``tamrm._native``, however spelled."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            hit = any(a.name == EXTENSION or a.name.startswith(EXTENSION + ".") for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            names = {a.name for a in node.names}
            if node.level == 0:
                hit = module == EXTENSION or module.startswith(EXTENSION + ".")
                hit = hit or (module == "tamrm" and "_native" in names)
            else:
                hit = module.split(".")[0] == "_native" or (not module and "_native" in names)
        else:
            # importlib.import_module("tamrm._native"), __import__(...)
            hit = isinstance(node, ast.Constant) and node.value == EXTENSION
        if hit:
            lines.append(getattr(node, "lineno", 0))
    return lines


def test_the_scan_sees_every_spelling() -> None:
    for code in [
        "import tamrm._native",
        "import tamrm._native as n",
        "from tamrm import _native",
        "from tamrm import _ops, _native",
        "from tamrm._native import Engine",
        "from . import _native",
        "from ._native import Engine",
        "importlib.import_module('tamrm._native')",
    ]:
        assert imports_the_extension(ast.parse(code)), code
    for code in ["from tamrm import _bridge", "self._native.step()", "import tamrm._bridge"]:
        assert not imports_the_extension(ast.parse(code)), code


def test_only_the_bridge_imports_the_native_extension() -> None:
    importers = {}
    for path in sources():
        lines = imports_the_extension(ast.parse(path.read_text(encoding="utf-8")))
        if lines:
            importers[rel(path)] = lines
    assert rel(BRIDGE) in importers, (
        "the bridge no longer imports the extension: is the scan blind?"
    )
    del importers[rel(BRIDGE)]
    assert not importers, (
        f"only {rel(BRIDGE)} imports {EXTENSION}; import what you need from tamrm._bridge "
        f"instead: {importers}"
    )


def stub_names() -> dict[str, set[str] | None]:
    """The public names of ``_native.pyi``: per class its public members, else ``None``."""
    tree = ast.parse((PACKAGE / "_native.pyi").read_text(encoding="utf-8"))
    names: dict[str, set[str] | None] = {}
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            members = set()
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    members.add(item.name)
                elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    members.add(item.target.id)
            names[node.name] = {m for m in members if not m.startswith("_")}
        elif isinstance(node, ast.FunctionDef):
            names[node.name] = None
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names[node.target.id] = None
    return {k: v for k, v in names.items() if not k.startswith("_")}


def test_the_stub_describes_the_built_extension() -> None:
    native = importlib.import_module(EXTENSION)
    built: dict[str, set[str] | None] = {}
    for name in dir(native):
        if name.startswith("_"):
            continue
        value = getattr(native, name)
        if isinstance(value, type):
            built[name] = {m for m in vars(value) if not m.startswith("_")}
        else:
            built[name] = None
    stub = stub_names()
    assert len(stub) >= 8, "the stub's names were not read: is the check blind?"
    assert stub == built, (
        "src/tamrm/_native.pyi and the built extension differ (stub, built): "
        + str(
            {
                k: (stub.get(k), built.get(k))
                for k in stub.keys() | built.keys()
                if stub.get(k, "-") != built.get(k, "-")
            }
        )
        + "; update the stub, or rebuild the extension (maturin develop)"
    )
