"""The code blocks of Markdown pages, run as written: the machinery of
``tests/test_readme.py`` (the README) and ``tests/test_docs_site.py`` (the pages
of ``docs/``).

A page's ``sh`` and ``python`` blocks run in order in one working directory (what
one block writes, such as ``rays.npy``, is there for the next), with this
interpreter's ``bin`` first on ``PATH`` (the docs' "venv on the PATH"): shell
blocks under ``bash -e -o pipefail`` (curl's ``--fail-with-body`` makes an error
answer fail the block), Python blocks as ``python -``. The only change made to a
block is the server's address: ``localhost:8000`` and ``127.0.0.1:8000`` (``make
run``'s) become the test server's.

A block is not run only when the line before its fence is a comment
``<!-- not run by tests/RUNNER.py: REASON -->`` naming the test module that would
run it; such a block is still checked to parse (``bash -n``, ``compile``).

Example
-------
>>> from tests.harness.blocks import markdown_blocks, not_run_marker   # doctest: +SKIP
>>> blocks = markdown_blocks(Path("README.md"), not_run_marker("test_readme"))
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

#: Fence languages that are run (a shell script, a Python program).
SHELL, PYTHON = "sh", "python"
#: Fence languages that are not code to run (synopses, trees, tables of output).
NOT_CODE = {"", "text"}
#: The addresses of ``make run``'s server, as the pages write them.
ADDRESSES = ("localhost:8000", "127.0.0.1:8000")
#: Seconds one block may take.
BLOCK_TIMEOUT = 600
_FENCE = re.compile(r"^```(\S*)\s*$")


@dataclass(frozen=True)
class Block:
    """One fenced block of a Markdown page.

    Attributes
    ----------
    source : str
        The page, as the block's name shows it (``README.md``, ``docs/fields.md``).
    line : int
        The line of the opening fence, 1-based.
    lang : str
        The fence's language (``sh``, ``python``, ``text`` or empty).
    text : str
        The block's lines, each ending in a newline.
    not_run : str or None
        Why the block is not run, when the line before its fence says so.
    """

    source: str
    line: int
    lang: str
    text: str
    not_run: str | None

    def __str__(self) -> str:
        return f"{self.source}:{self.line} ({self.lang})"

    @property
    def is_code(self) -> bool:
        """Whether the block is code (run, or parsed when marked not run)."""
        return self.lang not in NOT_CODE


def not_run_marker(runner: str) -> re.Pattern:
    """The comment that exempts a block from being run by ``tests/RUNNER.py``."""
    return re.compile(rf"^<!-- not run by tests/{re.escape(runner)}\.py: (?P<why>\S.*\S) -->$")


def markdown_blocks(path: Path, marker: re.Pattern, source: str | None = None) -> list[Block]:
    """The fenced blocks of a Markdown file, with the marker before each (if any).

    Parameters
    ----------
    path : Path
        The Markdown file.
    marker : re.Pattern
        :func:`not_run_marker` of the test module that runs the blocks.
    source : str, optional
        The page's name in the blocks' names (default the file's name).
    """
    source = source or path.name
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, lang = i, m.group(1)
        j = i + 1
        while j < len(lines) and lines[j].rstrip() != "```":
            j += 1
        assert j < len(lines), f"{source}:{start + 1}: a fence that is never closed"
        mark = marker.match(lines[start - 1]) if start else None
        blocks.append(Block(source, start + 1, lang, "\n".join(lines[start + 1:j]) + "\n",
                            mark.group("why") if mark else None))
        i = j + 1
    return blocks


def dangling_markers(path: Path, blocks: list[Block], marker: re.Pattern) -> list[int]:
    """Lines of markers that are not right before a code block's fence (1-based)."""
    marked = {b.line - 1 for b in blocks if b.is_code and b.not_run}
    lines = path.read_text(encoding="utf-8").splitlines()
    return [n + 1 for n, ln in enumerate(lines) if marker.match(ln) and n + 1 not in marked]


def check_parses(block: Block) -> None:
    """Assert that a block not run parses: ``bash -n`` or ``compile``."""
    if block.lang == SHELL:
        p = subprocess.run(["bash", "-n"], input=block.text, text=True, capture_output=True)
        assert p.returncode == 0, f"{block}: {p.stderr}"
    else:
        compile(block.text, str(block), "exec")


def block_env() -> dict:
    """The environment blocks run in: this one without ``FLATSERVE_*`` settings, with
    this interpreter's ``bin`` first on ``PATH``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLATSERVE_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def run_block(block: Block, url: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    """Run one block against the server at ``url`` (``http://HOST:PORT``)."""
    text = block.text
    host = url.removeprefix("http://")
    for addr in ADDRESSES:
        text = text.replace(addr, host)
    cmd = ["bash", "-e", "-o", "pipefail", "-s"] if block.lang == SHELL else [sys.executable, "-"]
    return subprocess.run(cmd, input=text, text=True, capture_output=True, cwd=cwd, env=env,
                          timeout=BLOCK_TIMEOUT)


def run_blocks(blocks: list[Block], url: str, cwd: Path, server_log: Path,
               rounds: int = 2) -> None:
    """Run the blocks in order, ``rounds`` times (each block must be rerunnable), and
    assert that each exits 0 and prints no error answer (``"detail"``) that did not fail
    it; a failure shows the block's output and the end of the server's log."""
    env = block_env()
    for rnd in range(1, rounds + 1):
        for block in blocks:
            p = run_block(block, url, cwd, env)
            log = server_log.read_text(errors="replace")[-3000:] if server_log.exists() else ""
            assert p.returncode == 0, (
                f"{block}, run {rnd}: exit {p.returncode}\n--- stdout\n{p.stdout[-3000:]}"
                f"\n--- stderr\n{p.stderr[-3000:]}\n--- server log\n{log}")
            assert '"detail"' not in p.stdout, f"{block}, run {rnd}: {p.stdout[-3000:]}"
