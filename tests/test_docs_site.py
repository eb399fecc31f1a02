"""The documentation site: ``mkdocs build --strict`` passes (a broken link, anchor, page
left out of the nav or API reference fails it), its HTTP reference covers every route
of the app's OpenAPI schema, and every ``sh`` and ``python`` block of the pages in
``docs/`` runs as written, twice, against a real server this test starts on a free
loopback port (as ``tests/test_readme.py`` runs the README's: ``tests/harness/blocks.py``).

Each page's blocks run in order in a working directory of that page's own; a block
that cannot run here says why on the line before its fence
(``<!-- not run by tests/test_docs_site.py: REASON -->``) and is checked to parse.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness.blocks import (PYTHON, SHELL, check_parses, dangling_markers, markdown_blocks,
                                  not_run_marker, run_blocks)
from tests.harness.process import ServerProcess

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MARKER = not_run_marker("test_docs_site")
PAGES = sorted(DOCS.rglob("*.md"))
BLOCKS = {p: markdown_blocks(p, MARKER, str(p.relative_to(ROOT))) for p in PAGES}
CODE = [b for blocks in BLOCKS.values() for b in blocks if b.is_code]
#: The pages with blocks to run, and those blocks.
RUN = {p: [b for b in blocks if b.is_code and b.not_run is None] for p, blocks in BLOCKS.items()}
RUN = {p: blocks for p, blocks in RUN.items() if blocks}
#: Seconds the strict build may take (it makes the app for the HTTP reference and reads
#: the package's docstrings).
BUILD_TIMEOUT = 300


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                        "-f", str(ROOT / "mkdocs.yml"), "-d", str(out)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=BUILD_TIMEOUT)
    assert p.returncode == 0, f"mkdocs build --strict failed:\n{p.stdout[-5000:]}\n{p.stderr[-5000:]}"
    return out


def test_the_site_builds_strictly_with_every_page(site):
    for page in PAGES:
        rel = page.relative_to(DOCS).with_suffix("")
        html = site / ("index.html" if rel.name == "index" else rel / "index.html")
        assert html.is_file(), f"{page} was not built"


def test_the_http_reference_is_the_apps_schema(site):
    from flatserve.service import Settings, create_app

    doc = create_app(Settings(data_dir=Path("unused"))).openapi()
    assert json.loads((site / "reference" / "openapi.json").read_text()) == doc
    page = (site / "reference" / "http" / "index.html").read_text(encoding="utf-8")
    for path, item in doc["paths"].items():
        for method in item:
            assert f"{method.upper()} <code>{path}</code>" in page, (method, path)


def test_the_api_reference_is_written_from_the_docstrings(site):
    page = (site / "reference" / "library" / "index.html").read_text(encoding="utf-8")
    import flatserve

    for name in ("Flats", "Basis", "Field", "AtlasField"):
        first = getattr(flatserve, name).__doc__.strip().splitlines()[0]
        assert f'id="flatserve.{name}"' in page, name
        assert first.split("``")[0].split("`")[0][:30] in page, (name, first)
    # the docstrings' Sphinx roles are shown as the code they mark (scripts/docs_roles.py),
    # their doctest lines as code, not as quotes (scripts/docs_doctest.py)
    for ref in ("library", "client", "lightfield"):
        html = (site / "reference" / ref / "index.html").read_text(encoding="utf-8")
        assert not re.search(r":(func|class|mod|meth|attr|data|exc):<code>", html), ref
        assert "<blockquote>" not in html, ref


def test_every_code_block_is_shell_or_python_and_run_unless_it_says_why():
    assert {b.lang for b in CODE} <= {SHELL, PYTHON}, [str(b) for b in CODE if b.lang not in (SHELL, PYTHON)]
    for page, blocks in BLOCKS.items():
        dangling = dangling_markers(page, blocks, MARKER)
        assert not dangling, f"{page}: markers not followed by a code fence at lines {dangling}"
    # every route a user calls is shown by a block that runs
    ran = "".join(b.text for blocks in RUN.values() for b in blocks)
    for what in ("/v1/fields -H", "/samples", "application/x-npy", "/query", "/render",
                 "/snapshot", "/export", "/import", "from flatserve.client import Client",
                 "import flatserve", "import_capture"):
        assert what in ran, f"no block that runs shows {what!r}"


@pytest.mark.parametrize("block", [b for b in CODE if b.not_run], ids=str)
def test_blocks_not_run_parse(block):
    check_parses(block)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("docs-server")
    log = tmp / "server.log"
    with ServerProcess(tmp / "data", log, snapshot_every=0) as srv:
        srv.wait_ready()
        yield srv, log


@pytest.mark.parametrize("page", list(RUN), ids=lambda p: str(p.relative_to(ROOT)))
def test_page_blocks_run_as_written_twice(page, server, tmp_path):
    srv, log = server
    run_blocks(RUN[page], srv.url, tmp_path, log)
