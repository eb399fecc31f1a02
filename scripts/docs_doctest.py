"""The documentation site's API reference: the docstrings' doctest examples as code.

A Griffe extension (``mkdocs.yml``: mkdocstrings' ``extensions``). The numpydoc
docstrings show examples as doctest lines (``>>> field.query(...)``) under an
``Example`` heading, which Markdown would read as nested quotes: each run of such
lines, from a ``>>>`` line to the next blank line, becomes a fenced ``pycon`` block.
"""
from __future__ import annotations

import re

from griffe import Extension

_PROMPT = re.compile(r"^(?P<indent>\s*)>>> ")


def fence_doctests(text: str) -> str:
    """The docstring with each run of doctest lines in a ``pycon`` fence."""
    lines, out, i = text.splitlines(), [], 0
    while i < len(lines):
        m = _PROMPT.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent, j = m.group("indent"), i
        while j < len(lines) and lines[j].strip():
            j += 1
        body = [ln[len(indent):] if ln.startswith(indent) else ln.lstrip() for ln in lines[i:j]]
        out += [f"{indent}```pycon", *(indent + ln for ln in body), f"{indent}```"]
        i = j
    return "\n".join(out)


class DoctestFences(Extension):
    """Fence the doctest examples of every docstring Griffe loads."""

    def on_object(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None and ">>> " in obj.docstring.value:
            obj.docstring.value = fence_doctests(obj.docstring.value)
