"""Hostile ``.npy`` / ``.npz`` bodies over HTTP: always a 4xx naming what is wrong,
never a 5xx, and the client (and, against a real server, the very same keep-alive
connection) can go on with its next request."""
from __future__ import annotations

import http.client
import io
import time
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.harness.fields import paper_rays
from tests.harness.hostile import (DEFLATED, Member, descr_header, npy, npy_bodies, npz,
                                  npz_bodies, raw_zip, zeros_bomb)
from tests.harness.process import ServerProcess

NPY, NPZ = "application/x-npy", "application/x-npz"


def _bomb() -> bytes:
    a, b = zeros_bomb(2**27, 1), zeros_bomb(2**27, 1)  # 2 x 1 GiB declared, ~2 MiB sent
    a.name, b.name = "origins.npy", "directions.npy"
    return raw_zip([a, b])


HOSTILE = {  # name: (body, content type, status, words the error must hold)
    "bool-shape": (descr_header((True, 6)) + bytes(48), NPY, 422, "True"),
    "negative-shape": (descr_header((-1, -6)) + bytes(48), NPY, 422, "-1"),
    "list-shape": (descr_header([1, 6]) + bytes(48), NPY, 422, "shape"),
    "bad-magic": (b"\x93NUMPX" + bytes(200), NPY, 422, "magic"),
    "long-header": (b"\x93NUMPY\x02\x00\xff\xff\xff\xff" + bytes(64), NPY, 422, "header"),
    "truncated-npy": (npy(np.zeros((4, 6)))[:-1], NPY, 422, "truncated"),
    "huge-npy": (descr_header((2**40, 6)) + bytes(48), NPY, 413, "1099511627776 rows"),
    "nested-zip": (raw_zip([Member("origins.npy", npz(origins=np.zeros((2, 3))))]), NPZ, 422,
                   "nested zip"),
    "raw-member": (raw_zip([Member("origins.npy", b"just bytes")]), NPZ, 422, "'origins.npy'"),
    "txt-member": (raw_zip([Member("notes.txt", b"hi")]), NPZ, 422, "'notes.txt'"),
    "duplicate": (raw_zip([Member("origins.npy", npy(np.zeros((2, 3))))] * 2), NPZ, 422,
                  "more than once"),
    "lying-size": (raw_zip([Member("origins.npy", npy(np.zeros((2, 3))), DEFLATED,
                                   file_size=10**6)]), NPZ, 422, "'origins.npy'"),
    "bool-member": (raw_zip([Member("origins.npy", descr_header((True, 3)) + bytes(24))]), NPZ,
                    422, "True"),
    "bomb": (_bomb(), NPZ, 413, "origins.npy"),
    "npz-as-npy": (npz(origins=np.zeros((2, 3))), NPY, 422, "the body is an .npz archive"),
}

# the fast query path, the FastAPI query route (a repeated parameter sends it there)
# and the upload route
TARGETS = ["/v1/fields/f/query", "/v1/fields/f/query?order=given&order=given",
           "/v1/fields/f/samples"]


@pytest.fixture
def field(api, rng):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 30)
    c.upload("f", rng.uniform(size=(30, 1)), origins=o, directions=v)
    q = np.c_[paper_rays(rng, 3)]
    return tc, c, npy(q)


def _still_serves(tc, query: bytes):
    r = tc.post("/v1/fields/f/query", content=query, headers={"Content-Type": NPY})
    assert r.status_code == 200, r.text
    assert tc.get("/healthz").status_code == 200


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_body_is_a_4xx_naming_what_is_wrong(field, case, target):
    tc, c, query = field
    body, ctype, status, words = HOSTILE[case]
    before = c.describe("f")["nsamples"]
    t0 = time.perf_counter()
    r = tc.post(target, content=body, headers={"Content-Type": ctype})
    assert r.status_code == status, (case, target, r.status_code, r.text)
    assert time.perf_counter() - t0 < 5, case  # refused, not inflated
    assert words in r.text, r.text
    if status == 422:
        assert r.json()["detail"][0]["loc"][0] == "body"
    assert c.describe("f")["nsamples"] == before
    _still_serves(tc, query)


HTTP_FUZZ = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                     suppress_health_check=[HealthCheck.function_scoped_fixture,
                                            HealthCheck.too_slow, HealthCheck.data_too_large])


@HTTP_FUZZ
@given(body=st.one_of(npy_bodies(), npz_bodies()), ctype=st.sampled_from([NPY, NPZ]),
       target=st.sampled_from(TARGETS))
def test_fuzzed_binary_bodies_never_give_a_5xx(field, body, ctype, target):
    tc, _, query = field
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = tc.post(target, content=body, headers={"Content-Type": ctype})
    # a fuzzed body may happen to be a valid upload or query (200); nothing else but 4xx
    assert r.status_code == 200 or 400 <= r.status_code < 500, (r.status_code, r.text)
    if r.status_code >= 400:
        assert r.json()["detail"]
    _still_serves(tc, query)


def test_real_server_keeps_the_connection_after_hostile_bodies(tmp_path, rng):
    """Against a real server: every hostile body gets its 4xx on ONE keep-alive
    connection, and that connection then serves a valid query."""
    with ServerProcess(tmp_path / "data", tmp_path / "server.log") as srv:
        srv.wait_ready()
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=30)

        def post(path, body, ctype="application/json"):
            conn.request("POST", path, body=body, headers={"Content-Type": ctype})
            resp = conn.getresponse()
            return resp.status, resp.read(), resp.getheader("connection")

        status, text, _ = post("/v1/fields", b'{"name": "f", "k": 1, "d": 3, "channels": 1}')
        assert status == 201, text
        o, v = paper_rays(rng, 30)
        status, text, _ = post("/v1/fields/f/samples", npy(np.c_[o, v, np.ones(30)]), NPY)
        assert status == 200, text
        sock = conn.sock
        for case, (body, ctype, want, _) in sorted(HOSTILE.items()):
            for target in TARGETS:
                status, text, connection = post(target, body, ctype)
                assert status == want, (case, target, status, text)
                assert connection != "close" and conn.sock is sock, (case, target)
        status, text, _ = post("/v1/fields/f/query", npy(np.c_[paper_rays(rng, 3)]), NPY)
        assert status == 200 and conn.sock is sock, text
        conn.close()


#: every route that reads a JSON body
JSON_TARGETS = ["/v1/fields", "/v1/fields/f/samples", "/v1/fields/f/query",
                "/v1/fields/f/query?order=given&order=given", "/v1/math/coordinates",
                "/v1/math/project", "/v1/fields/f/render"]


def test_real_server_answers_deeply_nested_json_with_a_422_and_keeps_the_connection(
        tmp_path, rng):
    """JSON nested 100,000 levels deep, as a body of every JSON route and as an
    import's manifest (read by the standard library's parser, whose RecursionError was
    a 500 that closed the connection): a 422 each, naming the manifest for the import,
    on ONE keep-alive connection that then serves a valid query."""
    with ServerProcess(tmp_path / "data", tmp_path / "server.log") as srv:
        srv.wait_ready()
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=30)

        def request(method, path, body=None, ctype="application/json"):
            conn.request(method, path, body=body,
                         headers={"Content-Type": ctype} if body is not None else {})
            resp = conn.getresponse()
            return resp.status, resp.read(), resp.getheader("connection")

        status, text, _ = request("POST", "/v1/fields",
                                  b'{"name": "f", "k": 1, "d": 3, "channels": 1}')
        assert status == 201, text
        o, v = paper_rays(rng, 30)
        status, text, _ = request("POST", "/v1/fields/f/samples", npy(np.c_[o, v, np.ones(30)]),
                                  NPY)
        assert status == 200, text
        status, export, _ = request("GET", "/v1/fields/f/export")
        assert status == 200, export
        sock = conn.sock
        deep = b"[" * 100_000 + b"]" * 100_000
        with np.load(io.BytesIO(export), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["manifest"] = np.frombuffer(deep, np.uint8)
        status, text, connection = request("POST", "/v1/fields/g/import", npz(**arrays), NPZ)
        assert status == 422 and b'"loc":["body","manifest"]' in text, (status, text)
        assert connection != "close" and conn.sock is sock
        for target in JSON_TARGETS:
            for body in (deep, b'{"origins": ' + deep + b', "directions": [[0, 0, 1]]}'):
                status, text, connection = request("POST", target, body)
                assert status == 422, (target, status, text[:300])
                assert connection != "close" and conn.sock is sock, target
        status, text, _ = request("POST", "/v1/fields/f/query", npy(np.c_[paper_rays(rng, 3)]),
                                  NPY)
        assert status == 200 and conn.sock is sock, text
        status, text, _ = request("GET", "/v1/fields")
        assert status == 200 and b'"g"' not in text, text  # the refused import made nothing
        conn.close()


#: (target, content type) of every body a route reads: the batch routes take the three
#: kinds, create and render take JSON only
EMPTY = [(t, c) for t in TARGETS for c in ("application/json", NPY, NPZ)] + [
    ("/v1/fields", "application/json"), ("/v1/fields/f/render", "application/json")]


@pytest.mark.parametrize("target,ctype", EMPTY)
def test_empty_body_is_a_422_that_says_the_body_was_empty(field, target, ctype):
    # curl --data-binary @FILE sends 0 bytes when FILE is missing: the answer says so
    tc, c, query = field
    before = c.describe("f")["nsamples"]
    r = tc.post(target, content=b"", headers={"Content-Type": ctype})
    assert r.status_code == 422, (target, ctype, r.status_code, r.text)
    assert r.json()["detail"][0]["loc"][0] == "body"
    assert "empty body (0 bytes)" in r.json()["detail"][0]["msg"], r.text
    assert c.describe("f")["nsamples"] == before
    _still_serves(tc, query)
