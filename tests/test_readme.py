"""The README runs as written: every ``sh`` and ``python`` block of README.md, in order,
twice (each block must be rerunnable), against a real server this test starts on a
free loopback port and a temporary data directory.

The only change made to a block is the server's address: ``localhost:8000`` and
``127.0.0.1:8000`` (``make run``'s) become the test server's. Blocks run in one
temporary working directory (what one block writes, such as ``rays.npy``, is there
for the next), with this interpreter's ``bin`` first on ``PATH`` (the README's
"venv on the PATH"); shell blocks under ``bash -e -o pipefail`` (curl's
``--fail-with-body`` makes an error answer fail the block), Python blocks as
``python -``. A block is not run only when the line before its fence is a comment
``<!-- not run by tests/test_readme.py: REASON -->``; those are still checked to
parse (``bash -n``, ``compile``).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from tests.harness.process import ServerProcess

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MARKER = re.compile(r"^<!-- not run by tests/test_readme\.py: (?P<why>\S.*\S) -->$")
SHELL, PYTHON = "sh", "python"
#: Fence languages that are not code to run (synopses, trees, tables of output).
NOT_CODE = {"", "text"}
ADDRESSES = ("localhost:8000", "127.0.0.1:8000")
BLOCK_TIMEOUT = 600


@dataclass(frozen=True)
class Block:
    line: int          # of the opening fence, 1-based
    lang: str
    text: str
    not_run: str | None  # the reason, when marked

    def __str__(self) -> str:
        return f"README.md:{self.line} ({self.lang})"


def readme_blocks(text: str) -> list[Block]:
    """The fenced blocks of a Markdown text, with the marker before each (if any)."""
    blocks, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^```(\S*)\s*$", lines[i])
        if not m:
            i += 1
            continue
        start, lang = i, m.group(1)
        j = i + 1
        while j < len(lines) and lines[j].rstrip() != "```":
            j += 1
        assert j < len(lines), f"README.md:{start + 1}: a fence that is never closed"
        mark = MARKER.match(lines[start - 1]) if start else None
        blocks.append(Block(start + 1, lang, "\n".join(lines[start + 1:j]) + "\n",
                            mark.group("why") if mark else None))
        i = j + 1
    return blocks


BLOCKS = readme_blocks(README.read_text(encoding="utf-8"))
CODE = [b for b in BLOCKS if b.lang not in NOT_CODE]
RUN = [b for b in CODE if b.not_run is None]


def test_every_code_block_is_shell_or_python_and_run_unless_it_says_why():
    assert {b.lang for b in CODE} <= {SHELL, PYTHON}, [str(b) for b in CODE]
    # a marker belongs to the fence right after it: none is left dangling
    marked = {b.line - 1 for b in CODE if b.not_run}
    text = README.read_text(encoding="utf-8").splitlines()
    dangling = [n + 1 for n, ln in enumerate(text) if MARKER.match(ln) and n + 1 not in marked]
    assert not dangling, f"markers not followed by a code fence at lines {dangling}"
    # what a newcomer does first is run, not only shown
    ran = "".join(b.text for b in RUN)
    for what in ("/v1/fields -H", "/samples", "application/x-npy", "/query", "/render",
                 "/snapshot", "/export", "/import", "from flatserve.client import Client",
                 "import flatserve"):
        assert what in ran, f"no block that runs shows {what!r}"


@pytest.mark.parametrize("block", [b for b in CODE if b.not_run], ids=str)
def test_blocks_not_run_parse(block):
    if block.lang == SHELL:
        p = subprocess.run(["bash", "-n"], input=block.text, text=True, capture_output=True)
        assert p.returncode == 0, f"{block}: {p.stderr}"
    else:
        compile(block.text, str(block), "exec")


def _run(block: Block, url: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    text = block.text
    host = url.removeprefix("http://")
    for addr in ADDRESSES:
        text = text.replace(addr, host)
    cmd = ["bash", "-e", "-o", "pipefail", "-s"] if block.lang == SHELL else [sys.executable, "-"]
    return subprocess.run(cmd, input=text, text=True, capture_output=True, cwd=cwd, env=env,
                          timeout=BLOCK_TIMEOUT)


def test_readme_blocks_run_as_written_twice(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLATSERVE_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    with ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every=0) as srv:
        srv.wait_ready()
        for rnd in (1, 2):
            for block in RUN:
                p = _run(block, srv.url, work, env)
                assert p.returncode == 0, (
                    f"{block}, run {rnd}: exit {p.returncode}\n--- stdout\n{p.stdout[-3000:]}"
                    f"\n--- stderr\n{p.stderr[-3000:]}\n--- server log\n"
                    + (tmp_path / "server.log").read_text(errors="replace")[-3000:])
                # an error answer printed by a command that did not fail the block
                assert '"detail"' not in p.stdout, f"{block}, run {rnd}: {p.stdout[-3000:]}"
    # what the blocks say they make
    assert (work / "view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    answer = np.load(work / "answer.npy")
    assert answer.shape == (1000, 2) and answer[:, 1].all()
