"""The lean ASGI path of POST /v1/fields/{name}/query answers exactly as the FastAPI
route does (the route serves whatever the fast path passes on)."""
from __future__ import annotations

import io

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.client import Client
from flatserve.service.http import query
from tests.harness.fields import KINDS, paper_rays

# an unknown query parameter makes the fast path pass the request on to FastAPI
ROUTE = {"via": "fastapi"}


def _npy(a):
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


@pytest.fixture(params=KINDS, ids=str)
def served(make_app, rng, request):
    """A field of each kind (the default atlas, one chart) with samples: ``(tc, kind)``."""
    with TestClient(base_url="http://127.0.0.1", app=make_app()) as tc:
        c = Client(http=tc)
        c.wait_ready(30)
        c.create_field("f", channels=2, basis=request.param.basis)
        o, v = paper_rays(rng, 600)
        c.upload_rays("f", o, v, rng.normal(size=(600, 2)))
        yield tc, request.param


@pytest.mark.parametrize("n", [1, 5, query.INLINE_ROWS + 10])  # inline and thread pool
@pytest.mark.parametrize("params", [{}, {"weights": "true", "outside": "clamp"},
                                    {"order": "given", "form": "rays", "wait": "1"}])
def test_same_answers_as_the_route(served, rng, n, params):
    tc, kind = served
    # an atlas field refuses weights=true (422 naming it), on both paths alike
    status = 422 if kind.atlas and "weights" in params else 200
    o, v = paper_rays(rng, n)
    url = "/v1/fields/f/query"
    js = {"origins": o.tolist(), "directions": v.tolist()}
    fast = tc.post(url, params=params, json=js)
    slow = tc.post(url, params={**params, **ROUTE}, json=js)
    assert fast.status_code == slow.status_code == status, fast.text
    assert fast.json() == slow.json()
    if status == 200:
        assert "query;dur=" in fast.headers["server-timing"]
    else:
        assert fast.json()["detail"][0]["loc"] == ["query", "weights"]
    hdr = {"Content-Type": "application/x-npy", "Accept": "application/x-npy"}
    fast = tc.post(url, params=params, content=_npy(np.c_[o, v]), headers=hdr)
    slow = tc.post(url, params={**params, **ROUTE}, content=_npy(np.c_[o, v]), headers=hdr)
    assert fast.status_code == slow.status_code == status
    assert fast.headers["content-type"] == slow.headers["content-type"]
    assert fast.content == slow.content


@pytest.mark.parametrize("case", ["unknown field", "bad name", "content type", "bad json",
                                  "shape", "non-finite", "bad param", "too many rows"])
def test_same_errors_as_the_route(make_app, case):
    with TestClient(base_url="http://127.0.0.1", app=make_app(max_batch_rows=3)) as tc:
        Client(http=tc).wait_ready(30)
        tc.post("/v1/fields", json={"name": "f"})
        url, params, kw = "/v1/fields/f/query", {}, {}
        ok = {"origins": [[0, 0, -3]], "directions": [[0, 0, 1]]}
        if case == "unknown field":
            url, kw = "/v1/fields/nope/query", {"json": ok}
        elif case == "bad name":
            url, kw = "/v1/fields/.x/query", {"json": ok}
        elif case == "content type":
            kw = {"content": b"x", "headers": {"Content-Type": "text/plain"}}
        elif case == "bad json":
            kw = {"content": b"{", "headers": {"Content-Type": "application/json"}}
        elif case == "shape":
            kw = {"json": {"origins": [[0, 0]], "directions": [[0, 0, 1]]}}
        elif case == "non-finite":
            kw = {"content": b'{"origins": [[0, 0, 1e999]], "directions": [[0, 0, 1]]}',
                  "headers": {"Content-Type": "application/json"}}
        elif case == "bad param":
            params, kw = {"outside": "sideways"}, {"json": ok}
        else:
            kw = {"json": {"origins": [[0, 0, -3]] * 4, "directions": [[0, 0, 1]] * 4}}
        fast = tc.post(url, params=params, **kw)
        slow = tc.post(url, params={**params, **ROUTE}, **kw)
        assert fast.status_code == slow.status_code and fast.status_code >= 400, case
        assert fast.json() == slow.json()


def test_api_keys_and_metrics_on_the_fast_path(make_app, rng):
    with TestClient(base_url="http://127.0.0.1", app=make_app(api_key="rw-key", read_only_key="ro-key")) as tc:
        Client(http=tc).wait_ready(30)
        c = Client(http=tc, api_key="rw-key")
        c.create_field("f")
        o, v = paper_rays(rng, 50)
        c.upload_rays("f", o, v, np.ones(50))
        del tc.headers["Authorization"]  # the Client set it on the shared TestClient
        js = {"origins": o[:3].tolist(), "directions": v[:3].tolist()}
        url = "/v1/fields/f/query"
        assert tc.post(url, json=js).status_code == 401
        assert tc.post(url, json=js, headers={"api-key": "wrong"}).status_code == 401
        assert tc.post(url, json=js, headers={"Authorization": "Bearer nope"}).status_code == 401
        for h in ({"api-key": "ro-key"}, {"Authorization": "Bearer ro-key"},
                  {"api-key": "rw-key"}):
            assert tc.post(url, json=js, headers=h).status_code == 200
        assert tc.get("/metrics").status_code == 401  # field names and counters need a key
        text = tc.get("/metrics", headers={"api-key": "ro-key"}).text
        assert ('flatserve_requests_total{method="POST",route="/v1/fields/{name}/query",'
                'status="200"} 3.0') in text
        assert 'flatserve_query_rows_total{field="f"} 9.0' in text
