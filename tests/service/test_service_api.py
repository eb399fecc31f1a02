"""The HTTP API in-process (TestClient): fields, uploads, queries, errors, keys."""
from __future__ import annotations

import io

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from flatserve import flats
from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.client import Client, ServiceError
from flatserve.coordinates import NO_SAMPLES, NOT_REPRESENTABLE, OK
from flatserve.errors import InvalidInputError as InvalidError
from flatserve.field import Field
from flatserve.service.rooms import specs
from flatserve.service.status import FieldExistsError as ConflictError
from flatserve.service.status import FieldNotFoundError as NotFoundError
from tests.harness.fields import KINDS, add_rays, paper_rays, query_rays

C = 3


def npy(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(arr))
    return buf.getvalue()


def npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_field_lifecycle(api):
    tc, c = api
    info = c.create_field("scene", channels=C, verbose=True)
    assert (info["k"], info["d"], info["channels"], info["nsamples"]) == (1, 3, C, 0)
    assert info["basis"]["m"] == 5 and np.asarray(info["basis"]["Q"]).shape == (5, 3, 3)
    # without basis: a covering atlas of lines (16 charts; `basis` describes chart 0)
    assert info["basis"]["spec"] == {"kind": "atlas", "atlas": "covering"}
    assert len(info["charts"]) == 16 and info["oriented"] is False
    assert [f["name"] for f in c.list_fields()] == ["scene"]
    with pytest.raises(ConflictError):
        c.create_field("scene")
    c.delete_field("scene")
    assert c.list_fields() == []
    with pytest.raises(NotFoundError):
        c.describe("scene")
    with pytest.raises(NotFoundError):
        c.delete_field("scene")


def test_create_and_describe_answer_a_summary_unless_verbose(api):
    # a one-line create gets a few hundred bytes, not kilobytes of matrices and centres
    tc, c = api
    r = tc.post("/v1/fields", json={"name": "f"})
    assert r.status_code == 201 and len(r.content) < 1200, len(r.content)
    short = r.json()
    assert short["ncharts"] == 16 and "charts" not in short and "Q" not in short["basis"]
    assert short["atlas"]["oriented"] is False and short["basis"]["spec"]["kind"] == "atlas"
    full = tc.get("/v1/fields/f?verbose=true").json()
    assert len(full["charts"]) == 16 and np.asarray(full["basis"]["Q"]).shape == (5, 3, 3)
    assert {k: v for k, v in full.items() if k != "charts"} == {
        **short, "basis": full["basis"], "position": full["position"]}
    assert tc.get("/v1/fields/f").json() == {**short, "position": tc.get("/v1/fields/f").json()["position"]}
    one = c.create_field("one", basis={"kind": "tangent_simplex"})
    assert one["ncharts"] == 1 and "charts" not in one and "atlas" not in one


def test_explicit_bases(api):
    tc, c = api
    ref = specs.build_basis(None, 1, 3)
    info = c.create_field("qr", basis={"kind": "flats", "Q": ref.Q.tolist(), "r": ref.r.tolist()},
                          verbose=True)
    assert np.allclose(info["basis"]["Q"], ref.Q)
    ts = c.create_field("ts", basis={"kind": "tangent_simplex", "scale": 0.02,
                                     "center": {"origin": [0, 0, 0], "direction": [0, 0, 1]}})
    assert ts["basis"]["spec"]["scale"] == 0.02
    r = tc.post("/v1/fields", json={"name": "bad", "basis": {"kind": "flats", "Q": ref.Q[:3].tolist(),
                                                              "r": ref.r[:3].tolist()}})
    assert r.status_code == 422 and "basis" in r.text


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_upload_forms_match_in_process_field(api, rng, kind):
    """JSON, .npy and .npz uploads of the same batches give the in-process field's answers
    (an AtlasField for the default, a Field for one chart)."""
    tc, c = api
    ref = kind.reference(C)
    batches = [paper_rays(rng, 300) + (rng.uniform(size=(300, C)),) for _ in range(3)]
    for name in ("json", "npy", "npz"):
        c.create_field(name, channels=C, basis=kind.basis)
    for o, v, val in batches:
        want = add_rays(ref, o, v, val)
        assert (want.accepted == 300) == kind.atlas  # one chart: some rays are beyond it
        got_json = c.upload_rays("json", o, v, val, binary=False)
        r = tc.post("/v1/fields/npy/samples", content=npy(np.c_[o, v, val].astype(np.float32)),
                    headers={"Content-Type": "application/x-npy"})
        assert r.status_code == 200, r.text
        got_npy = r.json()
        r = tc.post("/v1/fields/npz/samples", content=npz(origins=o, directions=v, values=val),
                    headers={"Content-Type": "application/x-npz"})
        got_npz = r.json()
        for got in (got_json, got_npz):
            assert got["accepted"] == want.accepted
            assert got["rejected"] == want.rejected.tolist()
            assert len(got["reasons"]) == len(got["rejected"])
            assert got["nsamples"] == want.nsamples
        # float32 transport rounds the rays: only the counts are comparable
        assert abs(got_npy["accepted"] - want.accepted) <= 3
    qo, qv = paper_rays(rng, 500)
    want = query_rays(ref, qo, qv, return_weights=not kind.atlas)
    for name in ("json", "npz"):
        for binary in (True, False):
            got = c.query_rays(name, qo, qv, binary=binary)
            np.testing.assert_array_equal(got.inside, want.inside)
            np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-12)
        if kind.atlas:  # several charts' ids are not returned
            with pytest.raises(InvalidError) as err:
                c.query_rays(name, qo, qv, weights=True)
            assert err.value.argument == "weights"
            continue
        got = c.query_rays(name, qo, qv, weights=True)
        np.testing.assert_array_equal(got.ids, want.ids)
        np.testing.assert_allclose(got.weights, want.weights, atol=1e-12)
        np.testing.assert_array_equal(got.status, want.status)


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_query_at_samples_returns_their_values(api, rng, kind):
    tc, c = api
    c.create_field("f", channels=C, basis=kind.basis)
    o, v = paper_rays(rng, 1000)
    val = rng.uniform(size=(1000, C))
    rep = c.upload_rays("f", o, v, val)
    ok = np.setdiff1d(np.arange(1000), rep["rejected"])
    assert rep["nsamples"] == ok.size == rep["accepted"]
    res = c.query_rays("f", o[ok], v[ok])
    assert res.inside.all()
    np.testing.assert_allclose(res.values, val[ok], atol=1e-9)
    if kind.atlas:  # every orientation is charted: nothing rejected
        assert rep["rejected"] == [] and rep["reasons"] == []
        return
    res = c.query_rays("f", o[ok], v[ok], weights=True)
    np.testing.assert_allclose(res.values, val[ok], atol=1e-9)
    # barycentric weights sum to one; ids are sample ids
    np.testing.assert_allclose(res.weights.sum(axis=1), 1.0, atol=1e-9)
    assert res.ids.max() < rep["nsamples"]
    # the rejected rays are reported NOT inside (outside the chart)
    bad = np.asarray(rep["rejected"])
    if bad.size:
        assert not c.query_rays("f", o[bad], v[bad]).inside.any()


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_query_response_formats_agree(api, rng, kind):
    tc, c = api
    c.create_field("f", channels=2, basis=kind.basis)
    o, v = paper_rays(rng, 400)
    c.upload_rays("f", o, v, rng.normal(size=(400, 2)))
    qo, qv = paper_rays(rng, 50)
    body = npy(np.c_[qo, qv])
    j = tc.post("/v1/fields/f/query", content=body, headers={"Content-Type": "application/x-npy"})
    assert j.headers["content-type"].startswith("application/json")
    jj = j.json()
    weights = "false" if kind.atlas else "true"  # (an atlas field refuses weights=true)
    n = tc.post(f"/v1/fields/f/query?weights={weights}", content=body,
                headers={"Content-Type": "application/x-npy", "Accept": "application/x-npy"})
    arr = np.load(io.BytesIO(n.content))
    assert arr.shape == (50, 2 + 1 + (0 if kind.atlas else 2 * 5))
    assert "query;dur=" in n.headers["server-timing"]
    vals = np.array([[np.nan if x is None else x for x in row] for row in jj["values"]])
    np.testing.assert_allclose(arr[:, :2], vals, atol=0, equal_nan=True)
    np.testing.assert_array_equal(arr[:, 2] == 1, jj["inside"])


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_parametric_and_qr_forms(api, rng, kind):
    """(A, b) and (Q, r) forms give the in-process field's answers; inside the hull the
    value at a sample is the sample's value."""

    tc, c = api
    ref = kind.reference(1)
    c.create_field("f", channels=1, basis=kind.basis)
    o, v = paper_rays(rng, 300)
    Q, r = flats.from_rays(o, v)
    A, b = flats.to_parametric(Q, r, 1)
    val = rng.uniform(size=(300, 1))
    rep = c.upload_parametric("f", A, b, val)
    want_add = ref.add(flats.Flats.from_parametric(A, b), val)
    assert rep["rejected"] == want_add.rejected.tolist()
    ok = np.setdiff1d(np.arange(300), rep["rejected"])
    want = ref.query(flats.Flats.from_quadrics(Q[ok], r[ok], 1))
    # (with the default atlas's narrow charts more of 300 samples lie on their hulls)
    assert want.inside.mean() > 0.7
    np.testing.assert_allclose(want.values[want.inside], val[ok][want.inside], atol=1e-9)
    for res in (c.query_flats("f", Q[ok], r[ok]), c.query_flats("f", Q[ok], r[ok], binary=False)):
        np.testing.assert_array_equal(res.inside, want.inside)
        np.testing.assert_allclose(res.values, want.values, atol=1e-12, equal_nan=True)
    want = ref.query(flats.Flats.from_parametric(A[ok], b[ok]))
    res = c.query_parametric("f", A[ok], b[ok])
    np.testing.assert_array_equal(res.inside, want.inside)
    np.testing.assert_allclose(res.values, want.values, atol=1e-12, equal_nan=True)


def test_idempotency_key(api, rng):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 200)
    val = rng.uniform(size=(200, 1))
    first = c.upload_rays("f", o, v, val, idempotency_key="batch-1")
    again = c.upload_rays("f", o, v, val, idempotency_key="batch-1", binary=False)
    assert again["replayed"] and not first["replayed"]
    assert {k: again[k] for k in first if k != "replayed"} == \
        {k: first[k] for k in first if k != "replayed"}
    assert len(c.batches("f")) == 1
    assert c.describe("f")["nsamples"] == first["nsamples"]
    with pytest.raises(InvalidError) as err:
        c.upload_rays("f", o, v, val + 1, idempotency_key="batch-1")
    assert err.value.status == 422 and "Idempotency-Key" in str(err.value)
    assert len(c.batches("f")) == 1


@pytest.mark.parametrize("body, ctype, status, where", [
    (b'{"origins": [[0,0,0]], "directions": [[0,0,1]], "values": [[1], [2]]}',
     "application/json", 422, "values"),
    (b'{"origins": [[0,0]], "directions": [[0,0,1]], "values": [[1]]}', "application/json", 422,
     "origins"),
    (b'{"origins": [[0,0,0]], "directions": [[0,0,1e999]], "values": [[1]]}', "application/json",
     422, "body"),
    (b'{"origins": [[0,0,0]], "directions": [[0,0,0]], "values": [[1]]}', "application/json",
     422, "directions"),
    (b'{"origins": [[0,0,0]], "directions": [[0,0,1]], "values": [["x"]]}', "application/json", 422,
     "values"),
    (b'{"A": [[0,0,0]]}', "application/json", 422, "A"),
    (b'{"origins": [[0,0,0]], "directions": [[true,0,1]], "values": [[1]]}',
     "application/json", 422, "directions"),
    (b'{"origins": [[0,0,0]], "directions": [[0,0,1]], "values": [[false]]}',
     "application/json", 422, "values"),
    (b"not json", "application/json", 422, "body"),
    (b"[1, 2]", "application/json", 422, "body"),
    (b"\x93NUMPY garbage", "application/x-npy", 422, "body"),
    (b"PK garbage", "application/x-npz", 422, "body"),
    (b"hello", "text/plain", 415, None),
    (b"hello", "multipart/form-data", 415, None),
])
def test_bad_uploads_are_4xx_naming_the_argument(api, body, ctype, status, where):
    tc, c = api
    c.create_field("f", channels=1)
    r = tc.post("/v1/fields/f/samples", content=body, headers={"Content-Type": ctype})
    assert r.status_code == status, r.text
    if where:
        assert r.json()["detail"][0]["loc"][-1] == where
    assert c.describe("f")["nsamples"] == 0


@pytest.mark.parametrize("path", ["samples", "query"])
def test_flats_of_another_kind_are_refused_naming_the_field_and_its_kind(api, path):
    """Planes in R^4 sent to a field of lines in R^3: the 422 names the array,
    its shapes, the field and what it holds."""
    tc, c = api
    c.create_field("f", channels=1)
    body = {"A": np.zeros((1, 4, 2)).tolist(), "b": np.zeros((1, 4)).tolist()}
    if path == "samples":
        body["values"] = [[1.0]]
    r = tc.post(f"/v1/fields/f/{path}", json=body)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"][-1] == "A"
    assert "expected shape (n, 3, 1), got (1, 4, 2)" in detail["msg"]
    assert "field 'f' holds lines in R^3 (k=1, d=3)" in detail["msg"]


@pytest.mark.parametrize("path", ["samples", "query"])
@pytest.mark.parametrize("ctype", ["json", "npy", "npz"])
def test_points_sent_to_a_field_of_lines_are_refused_naming_the_field(api, path, ctype):
    """The points form is for k = 0 only: sent to lines in R^3 (by JSON or .npz names,
    or form=points with an .npy) the 422 names the form, the field and its (k, d)."""
    tc, c = api
    c.create_field("f", channels=1)
    P = np.zeros((2, 3))
    vals = np.ones((2, 1))
    up = path == "samples"
    if ctype == "json":
        kw = {"json": {"points": P.tolist(), **({"values": vals.tolist()} if up else {})}}
    elif ctype == "npz":
        kw = {"content": npz(points=P, **({"values": vals} if up else {})),
              "headers": {"Content-Type": "application/x-npz"}}
    else:
        kw = {"content": npy(np.c_[P, vals] if up else P), "params": {"form": "points"},
              "headers": {"Content-Type": "application/x-npy"}}
    r = tc.post(f"/v1/fields/f/{path}", **kw)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"][-1] == "form", detail
    assert "points are 0-flats (k = 0)" in detail["msg"], detail
    assert "field 'f' holds lines in R^3 (k=1, d=3)" in detail["msg"], detail
    assert c.describe("f")["nsamples"] == 0


@pytest.mark.parametrize("d", [2, 3])
def test_points_field_over_http_answers_as_scipy(api, d):
    """A field of points (k = 0) uploaded and queried in the `points` form (client .npy,
    JSON, .npz) and in the (n, d, 0) parametric form answers as scipy's
    LinearNDInterpolator on the same points in general position; points of another d
    are refused naming the shapes and the field."""
    from scipy.interpolate import LinearNDInterpolator

    tc, c = api
    rng = np.random.default_rng(40 + d)
    P = rng.uniform(-1, 1, (300, d))
    V = np.c_[np.sin(3 * P.sum(axis=1)), P[:, 0] ** 2]
    q = rng.uniform(-1.1, 1.1, (200, d))
    ref = LinearNDInterpolator(P, V)(q)
    inside = ~np.isnan(ref).any(axis=1)
    assert 0 < inside.sum() < len(q)

    def check(out):
        np.testing.assert_array_equal(out.inside, inside)
        np.testing.assert_allclose(out.values[inside], ref[inside], rtol=0, atol=1e-12)

    c.create_field("pts", k=0, d=d, channels=2)
    assert c.upload_points("pts", P, V)["accepted"] == len(P)
    c.create_field("par", k=0, d=d, channels=2)
    assert c.upload("par", V, A=np.zeros((len(P), d, 0)), b=P)["accepted"] == len(P)
    for name in ("pts", "par"):
        check(c.query_points(name, q))                 # .npy, form=points
        check(c.query_points(name, q, binary=False))   # JSON
        check(c.query(name, flats.Flats.from_points(q)))
        check(c.query(name, A=np.zeros((len(q), d, 0)), b=q))
    r = tc.post("/v1/fields/pts/query", content=npy(q),   # .npy without form: points
                headers={"Content-Type": "application/x-npy", "Accept": "application/x-npz"})
    assert r.status_code == 200, r.text
    with np.load(io.BytesIO(r.content)) as z:
        np.testing.assert_array_equal(z["inside"], inside)
        np.testing.assert_allclose(z["values"][inside], ref[inside], rtol=0, atol=1e-12)
    r = tc.post("/v1/fields/pts/query", content=npz(points=q),
                headers={"Content-Type": "application/x-npz", "Accept": "application/x-npz"})
    assert r.status_code == 200, r.text
    batches = c.batches("pts")
    assert [b["form"] for b in batches] == ["points"]
    r = tc.post("/v1/fields/pts/query", json={"points": np.zeros((1, d + 1)).tolist()})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"][-1] == "points"
    assert f"expected shape (n, {d}), got (1, {d + 1})" in detail["msg"]
    assert f"field 'pts' holds points in R^{d} (k=0, d={d})" in detail["msg"]


def orjson_bytes(obj) -> bytes:
    return orjson.dumps(obj)


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.parametrize("sent, ctype, says, is_", [
    ("npy", "application/json", "application/json", "application/x-npy"),
    ("npz", "application/json", "application/json", "application/x-npz"),
    ("json", "application/x-npy", "application/x-npy", "application/json"),
    ("npz", "application/x-npy", "application/x-npy", "application/x-npz"),
    ("npy", "application/x-npz", "application/x-npz", "application/x-npy"),
])
@pytest.mark.parametrize("path", ["samples", "query"])
def test_a_body_of_another_kind_than_its_content_type_says_so(api, rng, sent, ctype, says, is_,
                                                               path):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 5)
    body = {"npy": npy(np.c_[o, v, np.ones(5)]),
            "npz": _npz_bytes(origins=o, directions=v, values=np.ones((5, 1))),
            "json": orjson_bytes({"origins": o.tolist(), "directions": v.tolist(),
                                  "values": np.ones((5, 1)).tolist()})}[sent]
    r = tc.post(f"/v1/fields/f/{path}", content=body, headers={"Content-Type": ctype})
    assert r.status_code == 422, r.text
    msg = r.json()["detail"][0]["msg"]
    assert "the Content-Type says" in msg and f"({says})" in msg, msg
    assert f"send it with Content-Type: {is_}" in msg, msg
    assert c.describe("f")["nsamples"] == 0


def test_non_finite_npy_and_wrong_width(api):
    tc, c = api
    c.create_field("f", channels=1)
    a = np.zeros((4, 7))
    a[2, 3] = np.nan
    r = tc.post("/v1/fields/f/samples", content=npy(a), headers={"Content-Type": "application/x-npy"})
    assert r.status_code == 422 and "directions" in r.text and "[2]" in r.text
    r = tc.post("/v1/fields/f/samples", content=npy(np.zeros((4, 9))),
                headers={"Content-Type": "application/x-npy"})
    assert r.status_code == 422 and "(n, 7)" in r.text
    r = tc.post("/v1/fields/f/samples", content=npy(np.array(["a", "b"])),
                headers={"Content-Type": "application/x-npy"})
    assert r.status_code == 422


def test_names_and_unknown_fields(api):
    tc, c = api
    for bad in ["../etc", ".hidden", "a/b", "x" * 65, "", "a b"]:
        r = tc.post("/v1/fields", json={"name": bad})
        assert r.status_code == 422, bad
    assert tc.get("/v1/fields/..%2Fetc").status_code in (404, 422)
    assert tc.get("/v1/fields/nope").status_code == 404
    assert tc.post("/v1/fields/nope/query", json={"origins": [[0, 0, 0]],
                                                  "directions": [[0, 0, 1]]}).status_code == 404
    assert tc.post("/v1/fields", json={"name": "ok", "k": 3, "d": 3}).status_code == 422


def test_limits(make_app, rng):
    app = make_app(max_body_bytes=20_000, max_batch_rows=100, max_fields=2)
    with TestClient(base_url="http://127.0.0.1", app=app) as tc:
        c = Client(http=tc)
        c.wait_ready()
        c.create_field("a")
        c.create_field("b")
        with pytest.raises(ConflictError) as e:
            c.create_field("c")
        assert "limit" in str(e.value)
        o, v = paper_rays(rng, 101)
        r = tc.post("/v1/fields/a/samples", content=npy(np.c_[o, v, np.ones(101)]),
                    headers={"Content-Type": "application/x-npy"})
        assert r.status_code == 413 and "100" in r.text
        o, v = paper_rays(rng, 400)
        r = tc.post("/v1/fields/a/samples", content=npy(np.c_[o, v, np.ones(400)]),
                    headers={"Content-Type": "application/x-npy"})
        assert r.status_code == 413 and "bytes" in r.text

        def chunks():
            for _ in range(30):
                yield b"x" * 1000

        r = tc.post("/v1/fields/a/samples", content=chunks(),
                    headers={"Content-Type": "application/x-npy"})
        assert r.status_code == 413


def test_api_keys(make_app):
    app = make_app(api_key="rw-secret", read_only_key="ro-secret")
    with TestClient(base_url="http://127.0.0.1", app=app) as tc:
        assert tc.get("/healthz").status_code == 200
        assert tc.get("/v1/fields").status_code == 401
        assert tc.get("/v1/fields", headers={"api-key": "wrong"}).status_code == 401
        ro = {"Authorization": "Bearer ro-secret"}
        rw = {"api-key": "rw-secret"}
        assert tc.get("/v1/fields", headers=ro).status_code == 200
        assert tc.post("/v1/fields", json={"name": "f"}, headers=ro).status_code == 403
        assert tc.post("/v1/fields", json={"name": "f"}, headers=rw).status_code == 201
        body = {"origins": [[0, 0, -3]], "directions": [[0, 0, 1]]}
        assert tc.post("/v1/fields/f/query", json=body, headers=ro).status_code == 200
        assert tc.post("/v1/fields/f/samples", json={**body, "values": [[1]]},
                       headers=ro).status_code == 403
        assert tc.delete("/v1/fields/f", headers=ro).status_code == 403
        assert tc.delete("/v1/fields/f", headers=rw).status_code == 204


def test_settings_reject_bad_key_setups():
    from pydantic import ValidationError

    from flatserve.service import Settings

    with pytest.raises(ValidationError):
        Settings(read_only_key="x")
    with pytest.raises(ValidationError):
        Settings(api_key="x", read_only_key="x")
    assert Settings(host="0.0.0.0").bind_host() == "127.0.0.1"
    assert Settings(host="0.0.0.0", api_key="k").bind_host() == "0.0.0.0"


def test_settings_from_environment(monkeypatch, tmp_path):
    from flatserve.service import Settings

    monkeypatch.setenv("FLATSERVE_PORT", "9123")
    monkeypatch.setenv("FLATSERVE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("FLATSERVE_MAX_FIELDS", "7")
    s = Settings()
    assert (s.port, s.data_dir, s.max_fields) == (9123, tmp_path, 7)


def test_metrics_and_health(api, rng):
    tc, c = api
    assert c.health() == {"status": "ok"}
    assert tc.get("/readyz").json()["status"] == "ready"
    c.create_field("f")
    o, v = paper_rays(rng, 100)
    rep = c.upload_rays("f", o, v, np.ones(100))
    c.query_rays("f", o, v)
    text = c.metrics()
    assert f'flatserve_samples_accepted_total{{field="f",replica="0"}} {float(rep["accepted"])}' \
        in text
    assert 'flatserve_query_rows_total{field="f"} 100.0' in text
    assert 'flatserve_requests_total{method="POST",route="/v1/fields/{name}/query",status="200"}' \
        in text
    assert "flatserve_request_seconds_bucket" in text
    assert f'flatserve_field_samples{{field="f",replica="0"}} {float(rep["nsamples"])}' in text
    assert "_created" not in text  # no creation-time series
    assert 'flatserve_replica_resident_bytes{replica="0"}' in text
    assert "process_cpu_seconds_total" in text  # one process: the standard process series


def test_math_endpoints_match_library(api, rng):

    tc, c = api
    o, v = paper_rays(rng, 20)
    basis = specs.build_basis(None, 1, 3)
    want = basis.coordinates(*flats.from_rays(o, v))
    got = c.coordinates(origins=o, directions=v, embed=True)
    np.testing.assert_allclose(got["weights"], want.weights, atol=1e-12)
    np.testing.assert_array_equal(got["status"], want.status)
    assert got["embedded"].shape == (20, 4)
    w = rng.dirichlet(np.ones(5), size=7)
    p = c.project(w, Q=basis.Q, r=basis.r)
    ref = flats.affine_combination(w, basis.Q, basis.r, 1)
    np.testing.assert_allclose(p["Q"], ref.Q, atol=1e-12)
    np.testing.assert_allclose(p["r"], ref.r, atol=1e-12)
    r = tc.post("/v1/math/project", json={"weights": [[0.5, 0.6, 0, 0, 0]],
                                          "flats": {"Q": basis.Q.tolist(), "r": basis.r.tolist()}})
    assert r.status_code == 422


def test_empty_idempotency_key_means_no_key(api, rng):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 50)
    body = npy(np.c_[o, v, rng.uniform(size=(50, 1))])
    for _ in range(2):
        r = tc.post("/v1/fields/f/samples?form=rays", content=body,
                    headers={"content-type": "application/x-npy", "Idempotency-Key": ""})
        assert r.status_code == 200 and not r.json()["replayed"]
    assert len(c.batches("f")) == 2


def test_npz_arrays_of_non_real_dtype_are_422(api, rng):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 3)
    body = npz(origins=o.astype(complex), directions=v)
    r = tc.post("/v1/fields/f/query", content=body, headers={"content-type": "application/x-npz"})
    assert r.status_code == 422 and "origins" in r.text


def test_a_roundtrip_tol_below_rounding_is_422(api):
    tc, c = api
    for tol in (1e-300, 1e-16, 0.0):
        r = tc.post("/v1/fields", json={"name": "t", "roundtrip_tol": tol})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "roundtrip_tol"
    assert c.create_field("t", roundtrip_tol=1e-15)["name"] == "t"


@pytest.mark.parametrize("path", ["samples", "query"])
def test_npz_members_no_form_has_are_422_naming_them(api, rng, path):
    """As in JSON: a misspelt or foreign array is refused, not ignored."""
    tc, c = api
    c.create_field("f", channels=1)
    o, v = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    extra = {"values": np.zeros((4, 1))} if path == "samples" else {}
    for bad in ("value", "weights"):
        r = tc.post(f"/v1/fields/f/{path}", content=npz(origins=o, directions=v, **extra,
                                                         **{bad: np.zeros((4, 1))}),
                    headers={"Content-Type": "application/x-npz"})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == bad, r.text
        assert "unknown member" in r.text
    assert c.describe("f")["storage"]["batches"] == 0


@pytest.mark.parametrize("encoding", ["json", "npy", "npz"])
@pytest.mark.parametrize("path", ["samples", "query"])
def test_zero_row_batches_are_422_in_every_encoding(api, encoding, path):
    """One rule whatever the transport: a batch has at least one row."""
    tc, c = api
    c.create_field("f", channels=1)
    z = np.zeros((0, 3))
    up = path == "samples"
    if encoding == "json":
        body = {"origins": [], "directions": []} | ({"values": []} if up else {})
        r = tc.post(f"/v1/fields/f/{path}", json=body)
    elif encoding == "npy":
        r = tc.post(f"/v1/fields/f/{path}", content=npy(np.zeros((0, 7 if up else 6))),
                    headers={"Content-Type": "application/x-npy"})
    else:
        arrs = {"origins": z, "directions": z} | ({"values": np.zeros((0, 1))} if up else {})
        r = tc.post(f"/v1/fields/f/{path}", content=npz(**arrs),
                    headers={"Content-Type": "application/x-npz"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == "origins" and "at least one row" in r.text
    if encoding == "npy":  # the client sends zero rows as they are: the same 422
        with pytest.raises(ServiceError) as err:
            if up:
                c.upload_rays("f", z, z, np.zeros((0, 1)))
            else:
                c.query_rays("f", z, z)
        assert err.value.status == 422 and "at least one row" in str(err.value)
    assert c.describe("f")["storage"]["batches"] == 0


def test_integer_and_float16_npy_bodies_are_read_as_float64(api, rng):
    """The documented dtype rule: any real number type, read as float64."""
    tc, c = api
    eyes = np.c_[rng.integers(-2, 3, (60, 2)), np.full(60, -8)]
    target = np.c_[rng.integers(-2, 3, (60, 2)), np.zeros(60)]
    rows = np.c_[eyes, target - eyes, rng.integers(0, 200, (60, 1))]  # small integers
    probe = (np.array([[0.1, 0.2, -8.0]]), np.array([[0.05, -0.1, 8.0]]))
    answers = []
    for dtype in (np.float64, np.int16, np.uint8 if rows.min() >= 0 else np.int32, np.float16):
        name = f"f{np.dtype(dtype).name}"
        c.create_field(name, channels=1)
        r = tc.post(f"/v1/fields/{name}/samples", content=npy(rows.astype(dtype)),
                    headers={"Content-Type": "application/x-npy"})
        assert r.status_code == 200, r.text
        answers.append((r.json()["accepted"], c.query_rays(name, *probe).values.tolist()))
    assert all(a == answers[0] for a in answers)


def test_basis_specs_kind_inferred_one_form_and_paths_in_errors(api):
    """`kind` may be left out (explicit flats when arrays are given); a centre or
    basis with two forms is refused; errors from inside a basis name its path."""
    tc, c = api
    ref = specs.build_basis(None, 1, 3)
    r = tc.post("/v1/fields", json={"name": "a", "basis": {"Q": ref.Q.tolist(), "r": ref.r.tolist()}})
    assert r.status_code == 201, r.text
    assert r.json()["basis"]["spec"]["kind"] == "flats"
    r = tc.post("/v1/fields", json={"name": "b", "basis": {"scale": 0.02}})
    assert r.status_code == 201 and r.json()["basis"]["spec"]["kind"] == "tangent_simplex"
    both = {"origin": [0, 0, 0], "direction": [0, 0, 1], "Q": np.eye(3).tolist(), "r": [0, 0, 0]}
    r = tc.post("/v1/fields", json={"name": "c", "basis": {"center": both}})
    assert r.status_code == 422 and "give one of" in r.text
    assert r.json()["detail"][0]["loc"][:3] == ["body", "basis", "tangent_simplex"]
    bad_dir = {"origin": [0, 0, 0], "direction": [0, 0, 0]}
    r = tc.post("/v1/fields", json={"name": "d", "basis": {"center": bad_dir}})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "basis", "center", "direction"], r.text
    notflat = np.eye(3) * 2
    r = tc.post("/v1/fields", json={"name": "e", "k": 1, "basis": {
        "center": {"Q": notflat.tolist(), "r": [0, 0, 0]}}})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "basis", "center", "Q"], r.text
    r = tc.post("/v1/fields", json={"name": "f", "basis": {"kind": "nonsense"}})
    assert r.status_code == 422
    assert [f["name"] for f in c.list_fields()] == ["a", "b"]


@pytest.mark.parametrize("unit", [5e-324, 1e-7, 2e6])
def test_a_unit_out_of_range_is_refused_naming_unit(api, unit):
    """(Found by the fuzzer's positive-data check: a subnormal unit was refused
    naming the atlas's centres.)"""
    tc, _ = api
    r = tc.post("/v1/fields", json={"name": "u", "k": 1, "d": 3, "unit": unit})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == "unit", r.text


def _near(rng, n, axis, half_deg):
    """Rays through [-1, 1]^3 whose directions lie within ``half_deg`` of ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    w = rng.normal(size=(n, 3))
    w -= (w @ a)[:, None] * a
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    t = np.radians(half_deg) * np.sqrt(rng.uniform(size=n))
    return rng.uniform(-1, 1, (n, 3)), np.cos(t)[:, None] * a + np.sin(t)[:, None] * w


@pytest.mark.parametrize("kind", ["one-chart", "default-atlas", "samples-atlas"])
def test_status_tells_empty_charts_from_unreachable_flats(api, rng, kind):
    """Empty, then partly filled: each transport answers the library's status per row;
    NO_SAMPLES (4) where the charts holding a flat have no simplex yet, NOT_REPRESENTABLE
    (1) where no chart holds it (the one chart's far side; beyond a samples atlas)."""
    tc, c = api
    near_z = flats.Flats.from_rays(*_near(rng, 400, [0, 0, 1], 30))
    if kind == "one-chart":
        basis, ref = {"kind": "tangent_simplex"}, Field(specs.build_basis(None, 1, 3), C)
    elif kind == "default-atlas":
        basis, ref = None, AtlasField(Atlas.covering(1, 3, unit="fit"), channels=C)
    else:
        o, v = near_z.arrays["origins"], near_z.arrays["directions"]
        basis = {"kind": "atlas", "atlas": "samples",
                 "samples": {"origins": o.tolist(), "directions": v.tolist()}}
        ref = AtlasField(Atlas.for_samples(near_z, unit="fit"), channels=C)
    c.create_field("st", channels=C, basis=basis)
    qo, qv = map(np.concatenate, zip(_near(rng, 150, [0, 0, 1], 10),
                                     _near(rng, 150, [1, 0, 0], 10)))  # near z; near x
    body = npy(np.c_[qo, qv])
    hdr = {"Content-Type": "application/x-npy"}

    def check(expected_codes):
        want = query_rays(ref, qo, qv)
        assert set(want.status.tolist()) == expected_codes
        for binary in (True, False):
            got = c.query_rays("st", qo, qv, binary=binary)
            np.testing.assert_array_equal(got.status, want.status)
            np.testing.assert_array_equal(got.inside, want.inside)
            np.testing.assert_allclose(got.values, want.values, atol=1e-12, equal_nan=True)
        plain = np.load(io.BytesIO(tc.post("/v1/fields/st/query", content=body,
                                           headers={**hdr, "Accept": "application/x-npy"}).content))
        assert plain.shape == (300, C + 1)  # without status=true: values | inside, as before
        r = tc.post("/v1/fields/st/query?status=true", content=body,
                    headers={**hdr, "Accept": "application/x-npy"})
        arr = np.load(io.BytesIO(r.content))
        assert arr.shape == (300, C + 2)
        np.testing.assert_array_equal(arr[:, :C + 1], plain)
        np.testing.assert_array_equal(arr[:, -1], want.status)
        r = tc.post("/v1/fields/st/query", content=body,
                    headers={**hdr, "Accept": "application/x-npz"})
        with np.load(io.BytesIO(r.content)) as z:
            np.testing.assert_array_equal(z["status"], want.status)
        j = tc.post("/v1/fields/st/query", content=body, headers=hdr).json()
        assert j["status"] == want.status.tolist()
        return want

    far = NO_SAMPLES if kind == "default-atlas" else NOT_REPRESENTABLE
    want = check({NO_SAMPLES, far})  # empty
    assert (want.status[:150] == NO_SAMPLES).all() and (want.status[150:] == far).all()
    o, v = _near(rng, 1500, [0, 0, 1], 20)
    val = rng.normal(size=(1500, C))
    c.upload_rays("st", o, v, val)
    add_rays(ref, o, v, val)
    want = check({OK, far})  # the charts near z filled; those near x still empty (or none)
    assert (want.status[:150] == OK).all() and (want.status[150:] == far).all()
