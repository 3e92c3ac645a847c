"""The report's prose: the blocks of ``templates/report.md`` with their placeholders filled.

A block starts at a line ``<!-- block: NAME -->`` and runs to the next such line; blank
lines around it are dropped. Placeholders are :class:`string.Template`'s (``$name``).
"""

from __future__ import annotations

import functools
import re
import string
from pathlib import Path

__all__ = ["TEMPLATE", "block", "block_lines"]

#: The template file.
TEMPLATE = Path(__file__).resolve().parent / "templates" / "report.md"

_MARKER = re.compile(r"^<!-- block: ([a-z0-9-]+) -->$", re.MULTILINE)


@functools.cache
def _blocks(path: Path = TEMPLATE) -> dict[str, str]:
    parts = _MARKER.split(path.read_text())
    blocks: dict[str, str] = {}
    for name, body in zip(parts[1::2], parts[2::2], strict=True):
        if name in blocks:
            raise ValueError(f"{path}: block {name!r} is defined twice")
        blocks[name] = body.strip("\n")
    return blocks


def block(name: str, **values: object) -> str:
    """Block ``name`` with ``values`` in its placeholders (``KeyError`` naming the block
    for a missing block or value)."""
    blocks = _blocks()
    if name not in blocks:
        raise KeyError(f"{TEMPLATE}: no block {name!r}")
    try:
        return string.Template(blocks[name]).substitute(values)
    except KeyError as exc:
        raise KeyError(f"{TEMPLATE}: block {name!r} needs a value for {exc}") from None


def block_lines(name: str, **values: object) -> list[str]:
    """:func:`block` as a list of lines."""
    return block(name, **values).split("\n")
