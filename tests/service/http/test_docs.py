"""The API documentation: ``/docs`` and ``/redoc`` from assets this server serves (no
CDN), rendered in a headless Chromium that can reach nothing but the server; request
examples for every body, valid requests one after another; every status the docs
promises documented."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from flatserve.service import Settings, create_app
from flatserve.service.http.docs import ASSETS_URL
from tests.harness.browser import chromium, serving, wait_for
from tests.harness.process import free_port

#: The page of the service's limits (its tables of what a client gets past each).
LIMITS_PAGE = Path(__file__).resolve().parents[3] / "docs" / "service.md"
#: No network but the server: every other host name fails to resolve.
OFFLINE_FLAGS = ["--window-size=1200,900",
                 "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"]
WAIT_S = 60.0


def _operations(doc: dict):
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            yield method.upper(), path, op


def test_docs_pages_load_their_assets_from_this_server(make_app):
    with TestClient(make_app(), base_url="http://127.0.0.1") as tc:
        for page in ("/docs", "/redoc"):
            html = tc.get(page).text
            urls = re.findall(r'(?:src|href)="([^"]+)"', html)
            assert urls and all(u.startswith(ASSETS_URL) for u in urls), (page, urls)
            assert "http" not in " ".join(urls) and "fonts.googleapis" not in html
            for u in urls:
                r = tc.get(u)
                assert r.status_code == 200 and len(r.content) > 1000, u


def test_every_body_has_an_example_and_the_examples_are_valid_requests(make_app):
    with TestClient(make_app(), base_url="http://127.0.0.1") as tc:
        doc = tc.get("/openapi.json").json()
        examples = {}
        for method, path, op in _operations(doc):
            body = op.get("requestBody")
            if body is None:
                continue
            if "application/json" not in body["content"]:  # a file (an import): binary
                assert body["content"] == {"application/x-npz": {
                    "schema": {"type": "string", "format": "binary"}}}, (method, path)
                continue
            assert "example" in body["content"]["application/json"], (method, path)
            examples[path] = body["content"]["application/json"]["example"]
        # in the order a newcomer would send them: create "demo", upload to it, query it ...
        order = ["/v1/fields", "/v1/fields/{name}/samples", "/v1/fields/{name}/query",
                 "/v1/fields/{name}/render", "/v1/math/coordinates", "/v1/math/project"]
        assert sorted(order) == sorted(examples)
        assert examples["/v1/fields"]["name"] == "demo"
        for path in order:
            r = tc.post(path.replace("{name}", "demo"), json=examples[path])
            assert r.status_code in (200, 201), (path, r.status_code, r.text)
        assert tc.get("/v1/fields/demo").json()["nsamples"] == 2


#: The header rows of the limits page's tables of what a client gets past a limit
LIMIT_TABLES = ("| setting (default) | past it |", "| setting | default | what |")


def _readme_statuses() -> set[int]:
    """The HTTP statuses of the limits page's tables: their last cells."""
    lines = LIMITS_PAGE.read_text(encoding="utf-8").splitlines()
    out: set[int] = set()
    for header in LIMIT_TABLES:
        i = lines.index(header) + 2
        while i < len(lines) and lines[i].startswith("|"):
            last = lines[i].strip().strip("|").split("|")[-1]
            out |= {int(x) for x in re.findall(r"\b([45]\d\d)\b", last)}
            i += 1
    return out


def test_every_status_the_readme_promises_is_documented(make_app):
    promised = _readme_statuses()
    assert {408, 409, 413, 429, 503, 507} <= promised
    doc = create_app(Settings(data_dir=Path("unused"))).openapi()
    documented = {int(s) for _, _, op in _operations(doc) for s in op["responses"]
                  if s.isdigit()}
    assert promised <= documented, promised - documented
    samples = doc["paths"]["/v1/fields/{name}/samples"]["post"]["responses"]
    assert {"413", "422", "429", "503", "507"} <= set(samples)


@pytest.fixture(scope="module")
def live_server(tmp_path_factory):
    port = free_port()
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("docs") / "data", port=port,
                              snapshot_every=0, access_log=False))
    with serving(app, port, WAIT_S) as url:
        yield url, app.openapi()


@pytest.fixture
def offline_browser(tmp_path):
    with chromium(tmp_path / "profile", OFFLINE_FLAGS, WAIT_S) as drv:
        yield drv


def _wait(fn, what: str):
    return wait_for(fn, what, WAIT_S, 0.2)


def test_docs_render_every_operation_without_a_network(live_server, offline_browser):
    url, doc = live_server
    ops = [(m, p) for m, p, _ in _operations(doc)]
    drv = offline_browser
    drv.get(f"{url}/docs")
    blocks = _wait(lambda: drv.find_elements("css selector", ".opblock-summary-path") or None,
                   "Swagger UI's operations")
    _wait(lambda: len(drv.find_elements("css selector", ".opblock-summary-path")) == len(ops),
          f"{len(ops)} operations")
    shown = {tuple(x) for x in drv.execute_script(
        "return [...document.querySelectorAll('.opblock')].map(b => ["
        "b.querySelector('.opblock-summary-method').textContent.trim(),"
        "b.querySelector('.opblock-summary-path').getAttribute('data-path')])")}
    assert shown == set(ops), set(ops) ^ shown
    assert blocks
    # the browser really is offline: the CDN that FastAPI's own page would use is not there
    drv.set_script_timeout(WAIT_S)
    cdn = drv.execute_async_script(
        "const done = arguments[0]; fetch('https://cdn.jsdelivr.net/npm/swagger-ui-dist@5/"
        "swagger-ui.css', {mode: 'no-cors'}).then(() => done('reached'), () => done('failed'));")
    assert cdn == "failed"
    drv.get(f"{url}/redoc")
    _wait(lambda: "Upload a batch of samples" in drv.find_element("tag name", "body").text,
          "ReDoc's operations")


def test_the_root_is_a_page_of_links_that_answer(make_app):
    """``GET /`` is a page of links (the docs, the schema, the fields, the limits, the
    viewer, health), each of which this server answers, and names no field it holds."""
    with TestClient(make_app(), base_url="http://127.0.0.1") as tc:
        r = tc.get("/")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        links = re.findall(r'href="([^"]+)"', r.text)
        assert {"/docs", "/redoc", "/openapi.json", "/v1/fields", "/v1/limits", "/healthz",
                "/readyz", "/metrics"} <= set(links)
        for link in links:
            if link.startswith("/viewer/"):
                continue  # the demo's field: the page is static, the field may not exist
            assert tc.get(link).status_code == 200, link
        assert tc.get(next(u for u in links if u.startswith("/viewer/"))).status_code == 200
