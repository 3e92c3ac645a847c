"""The documentation's rules that can be checked (CONTRIBUTING.md, "Where documentation
goes"): the README and the guides stay short, the guides hold current numbers rather than
dated run logs (those live in docs/lab/), no issue numbers, every relative link and
anchor in the Markdown resolves, and the Python modules the docs name exist."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
from conftest import REPO_ROOT

DOCS = REPO_ROOT / "docs"
#: Not written by hand: the contract (a faithful copy) and the generated report.
VERBATIM = {DOCS / "SPEC.md", DOCS / "reproduction.md"}
README_MAX_LINES = 200
GUIDE_MAX_LINES = 500


def markdown_files() -> list[Path]:
    """Every Markdown file of the README, CONTRIBUTING.md and docs/, the verbatim ones
    included (their links must resolve too)."""
    files = [REPO_ROOT / "README.md", REPO_ROOT / "CONTRIBUTING.md"]
    return files + sorted(DOCS.rglob("*.md"))


def guides() -> list[Path]:
    """The top-level documents of docs/: the user guides and the reference pages."""
    return [p for p in sorted(DOCS.glob("*.md")) if p not in VERBATIM]


def written_by_hand() -> list[Path]:
    return [p for p in markdown_files() if p not in VERBATIM]


def rel(path: Path) -> str:
    return str(path.relative_to(REPO_ROOT))


def prose(text: str) -> str:
    """The text without fenced code blocks (their lines blanked, so numbers stay)."""
    out, fenced = [], False
    for line in text.split("\n"):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append("")
        else:
            out.append("" if fenced else line)
    return "\n".join(out)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`([^`]*)`", r"\1", heading.strip())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    for line in prose(path.read_text(encoding="utf-8")).split("\n"):
        m = re.match(r"#{1,6} (.+)", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
    return found


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def links(path: Path) -> list[tuple[int, str]]:
    text = prose(path.read_text(encoding="utf-8"))
    text = re.sub(r"`[^`\n]*`", "", text)  # code spans hold no links
    return [
        (text.count("\n", 0, m.start()) + 1, m.group(1))
        for m in LINK.finditer(text)
        if not re.match(r"[a-z][a-z0-9+.-]*:", m.group(1))  # http:, https:, mailto:
    ]


def test_the_checks_see_the_docs() -> None:
    # Not vacuous: the files, links and anchors below are there to check.
    assert len(guides()) >= 10
    assert len(list((DOCS / "decisions").glob("*.md"))) >= 20
    assert sum(len(links(p)) for p in markdown_files()) >= 100
    assert "engine-remote-session-or-local-session" in anchors(DOCS / "python.md")
    assert slug("Fifth round: the server's allocator") == "fifth-round-the-servers-allocator"
    assert slug("The path of one `StepBatch`") == "the-path-of-one-stepbatch"


def test_readme_is_short() -> None:
    n = len((REPO_ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines, at most {README_MAX_LINES}"


@pytest.mark.parametrize("path", guides(), ids=rel)
def test_a_guide_is_at_most_500_lines(path: Path) -> None:
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= GUIDE_MAX_LINES, (
        f"{rel(path)} has {n} lines: split it by the reader's question (CONTRIBUTING.md)"
    )


DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
ROUND = re.compile(
    r"\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|\d+(st|nd|rd|th))"
    r"\s+round\b|\bround\s+\d+\b",
    re.I,
)


@pytest.mark.parametrize("path", guides(), ids=rel)
def test_a_guide_holds_no_dated_run_logs(path: Path) -> None:
    text = prose(path.read_text(encoding="utf-8"))
    text = re.sub(r"\[[^\]]*\]\([^)]*lab/[^)]*\)", "", text)  # a link to a lab notebook is fine
    text = re.sub(r"\]\([^)]*\)", "]()", text)
    problems = [
        f"{rel(path)}:{i}: {line.strip()}"
        for i, line in enumerate(text.split("\n"), 1)
        if DATE.search(line) or (line.startswith("#") and ROUND.search(line))
    ]
    assert not problems, (
        "dated runs and optimisation rounds go to docs/lab/YYYY-MM-DD-*.md; "
        "a guide keeps the current numbers:\n" + "\n".join(problems)
    )


ISSUE = re.compile(
    r"\bissues?\s*#?\s*\d+|\(issue\b|issues/\d+|(?<![\w#/&])#\d+\b",
    re.I,
)


@pytest.mark.parametrize("path", written_by_hand(), ids=rel)
def test_no_issue_numbers(path: Path) -> None:
    problems = [
        f"{rel(path)}:{i}: {line.strip()}"
        for i, line in enumerate(path.read_text(encoding="utf-8").split("\n"), 1)
        if ISSUE.search(line)
    ]
    assert not problems, "say what the thing is, not its issue number:\n" + "\n".join(problems)


@pytest.mark.parametrize("path", markdown_files(), ids=rel)
def test_relative_links_and_anchors_resolve(path: Path) -> None:
    problems = []
    for line, target in links(path):
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            problems.append(f"{rel(path)}:{line}: {target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{rel(path)}:{line}: {target}: no heading #{anchor}")
    assert not problems, "\n".join(problems)


def test_the_decisions_index_lists_every_decision() -> None:
    folder = DOCS / "decisions"
    index = folder / "README.md"
    listed = {target for _, target in links(index)}
    files = {p.name for p in folder.glob("*.md") if p != index}
    assert files - listed == set(), "decisions missing from docs/decisions/README.md"


def test_every_lab_notebook_is_linked_from_a_guide() -> None:
    linked: set[Path] = set()
    for path in markdown_files():
        if path.parent.name == "lab":
            continue
        for _, target in links(path):
            linked.add((path.parent / target.partition("#")[0]).resolve())
    orphans = [rel(p) for p in sorted((DOCS / "lab").glob("*.md")) if p.resolve() not in linked]
    assert not orphans, f"lab notebooks no guide links to: {orphans}"


SRC = REPO_ROOT / "clients" / "python" / "src"
#: The places whose Python names must exist: what a reader takes as the code of today.
#: (docs/lab/ holds dated records, which name the code as it was then.)
NAMING_DOCS = [
    REPO_ROOT / "README.md",
    REPO_ROOT / "CONTRIBUTING.md",
    REPO_ROOT / "clients" / "python" / "README.md",
    *sorted(DOCS.glob("*.md")),
    *sorted((DOCS / "decisions").glob("*.md")),
]
#: ``tamrm.<module>[.<name>]``, not inside a path, a file name or another dotted name.
PY_NAME = re.compile(r"(?<![\w./-])tamrm(?:\.[A-Za-z_]\w*)+")
#: ``tamrm/<path>.py`` (or ``.pyi``) and ``src/tamrm/<dir>/``, relative to clients/python/src.
PY_PATH = re.compile(
    r"(?<![\w./-])(?:clients/python/)?(?:src/)?(tamrm/(?:\w+/)*\w+\.pyi?|tamrm/(?:\w+/)+)(?![\w/])"
)
#: ``tamrm.<this>`` that is not Python: the proto's packages (``tamrm.v1.Shaping``), a host
#: name (``tamrm.example.com``) and files (``tamrm.toml``, ``tamrm.json``, ...).
NOT_PYTHON = {"v1", "v2", "example", "json", "toml", "key", "crt"}


def bound_names(module: Path) -> set[str]:
    """The names a module binds at its top level (also under ``if``/``try``)."""
    names: set[str] = set()
    body = list(ast.parse(module.read_text(encoding="utf-8")).body)
    while body:
        node = body.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.If):
            body += node.body + node.orelse
        elif isinstance(node, ast.Try):
            body += node.body + node.orelse + node.finalbody
            for handler in node.handlers:
                body += handler.body
    return names


def missing_python_name(name: str) -> str | None:
    """Why ``tamrm.a.b...`` names nothing in the sources (``None``: it does).

    Each segment is a package (a directory), a module (``.py``, or the extension's
    ``.pyi``), or a name its module binds; what follows a bound name (an attribute) is
    not checked.
    """
    directory: Path | None = SRC / "tamrm"
    module = SRC / "tamrm" / "__init__.py"
    for segment in name.split(".")[1:]:
        if directory is not None and (directory / segment).is_dir():
            directory = directory / segment
            module = directory / "__init__.py"
            continue
        files = [] if directory is None else [directory / (segment + s) for s in (".py", ".pyi")]
        found = [f for f in files if f.exists()]
        if found:
            directory, module = None, found[0]
            continue
        if not module.exists() or segment not in bound_names(module):
            return f"{segment!r} is no module of, nor a name in, {module.relative_to(SRC)}"
        return None
    return None


def python_names(path: Path) -> list[tuple[int, str]]:
    text = path.read_text(encoding="utf-8")
    found = []
    for m in PY_NAME.finditer(text):
        if m.group(0).split(".")[1] not in NOT_PYTHON:
            found.append((text.count("\n", 0, m.start()) + 1, m.group(0)))
    return found


def test_the_name_checks_see_stale_names() -> None:
    assert missing_python_name("tamrm.sb3.ShapedVecEnv") is None
    assert missing_python_name("tamrm._native.VecStep") is None
    assert missing_python_name("tamrm._proto.tamrm.v1") is None
    assert missing_python_name("tamrm.Client.session") is None
    assert missing_python_name("tamrm._stream.SessionCore") is not None
    assert missing_python_name("tamrm.rllib.NoSuchPiece") is not None
    assert [n for _, n in python_names(DOCS / "python.md")], "no names read: is the check blind?"
    assert PY_PATH.findall("`clients/python/src/tamrm/_proto/`, tamrm/gym.py") == [
        "tamrm/_proto/",
        "tamrm/gym.py",
    ]
    assert PY_PATH.findall("tamrm/reward_env, /etc/tamrm/server.crt, tamrm/v1/a.proto") == []


@pytest.mark.parametrize("path", NAMING_DOCS, ids=rel)
def test_the_python_modules_the_docs_name_exist(path: Path) -> None:
    problems = []
    for line, name in python_names(path):
        why = missing_python_name(name)
        if why is not None:
            problems.append(f"{rel(path)}:{line}: {name}: {why}")
    text = path.read_text(encoding="utf-8")
    for m in PY_PATH.finditer(text):
        if not (SRC / m.group(1)).exists():
            line = text.count("\n", 0, m.start()) + 1
            problems.append(f"{rel(path)}:{line}: {m.group(0)}: no such file in clients/python/src")
    assert not problems, "\n".join(problems)
