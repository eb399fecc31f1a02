"""The README runs as written: every ``sh`` and ``python`` block of README.md, in order,
twice (each block must be rerunnable), against a real server this test starts on a
free loopback port and a temporary data directory (``tests/harness/blocks.py`` says
how a block is run, and how one is marked not to be).
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.harness.blocks import (PYTHON, SHELL, check_parses, dangling_markers, markdown_blocks,
                                  not_run_marker, run_blocks)
from tests.harness.process import ServerProcess

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MARKER = not_run_marker("test_readme")
BLOCKS = markdown_blocks(README, MARKER)
CODE = [b for b in BLOCKS if b.is_code]
RUN = [b for b in CODE if b.not_run is None]
#: The README's length, at most (its detail lives in docs/).
MAX_LINES = 200


def test_every_code_block_is_shell_or_python_and_run_unless_it_says_why():
    assert {b.lang for b in CODE} <= {SHELL, PYTHON}, [str(b) for b in CODE]
    # a marker belongs to the fence right after it: none is left dangling
    dangling = dangling_markers(README, BLOCKS, MARKER)
    assert not dangling, f"markers not followed by a code fence at lines {dangling}"
    # the quick start's commands are shown, and what a newcomer does first is run
    shown = "".join(b.text for b in CODE)
    assert "make run" in shown and "make test" in shown
    ran = "".join(b.text for b in RUN)
    for what in ("/v1/fields -H", "from flatserve.client import Client",
                 "flatserve lightfield import", "import flatserve"):
        assert what in ran, f"no block that runs shows {what!r}"


def test_the_readme_is_short_and_links_only_to_files_that_exist():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= MAX_LINES
    targets = {m.split("#")[0] for m in re.findall(r"\]\(([^)\s]+)\)", text)}
    missing = [t for t in targets if not t.startswith("http") and not (ROOT / t).exists()]
    assert not missing, missing


@pytest.mark.parametrize("block", [b for b in CODE if b.not_run], ids=str)
def test_blocks_not_run_parse(block):
    check_parses(block)


def test_readme_blocks_run_as_written_twice(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    log = tmp_path / "server.log"
    with ServerProcess(tmp_path / "data", log, snapshot_every=0) as srv:
        srv.wait_ready()
        run_blocks(RUN, srv.url, work, log)
    # what the blocks say they make: a capture on disk, imported as a field
    assert (work / "capture" / "transforms.json").is_file()
