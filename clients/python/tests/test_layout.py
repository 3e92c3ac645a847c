"""The Python client's layout rules, read off its sources (as ``tests/layers.rs`` does for
the Rust crates; docs/architecture.md, "The Python client"): one module owns the native
extension, the extension's stub describes what it is built with, and a long module says
why it is one module."""

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


#: How many lines a module may have before it must say, at its top, why it is one module
#: (a line ``# Long file: <why>`` within its first 40 lines), as the Rust sources must
#: (docs/decisions/a-long-file-says-why.md): past that a module usually holds several
#: jobs, each of which reads better on its own.
LONG_FILE = 500
#: Written by scripts/gen_protos.py from proto/, never by hand.
GENERATED = PACKAGE / "_proto"


def long_file_reason(text: str) -> str | None:
    """The reason a ``# Long file: <why>`` line in the first 40 lines gives, if any."""
    for line in text.splitlines()[:40]:
        stripped = line.strip()
        if stripped.lower().startswith("# long file:"):
            return stripped[len("# long file:") :].strip() or None
    return None


def test_the_reason_is_read_off_the_top() -> None:
    assert long_file_reason('"""Doc."""\n\n# Long file: one table.\nX = 1\n') == "one table."
    assert long_file_reason("# Long file:\n") is None
    assert long_file_reason("\n" * 40 + "# Long file: too far down\n") is None


def test_a_long_module_says_why_it_is_one_module() -> None:
    longest = 0
    problems = []
    for path in sorted([*PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.pyi")]):
        if GENERATED in path.parents:
            continue
        text = path.read_text(encoding="utf-8")
        lines = len(text.splitlines())
        longest = max(longest, lines)
        if lines > LONG_FILE and long_file_reason(text) is None:
            problems.append(f"{rel(path)} has {lines} lines")
    assert longest > 100, f"the longest module has {longest} lines: is the check blind?"
    assert not problems, (
        f"more than {LONG_FILE} lines: split the module by job, or say why it is one module "
        f"in a line `# Long file: <why>` at its top: {problems}"
    )
