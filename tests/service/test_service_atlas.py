"""Atlas fields over HTTP (the default without ``basis``, or ``basis: {"kind": "atlas"}``):
every orientation accepted,
answers equal the library's :class:`flatserve.atlas_field.AtlasField`, restore from batches
and from a snapshot, ``wait=false``, oriented fields take rays only, describe lists
the charts."""
from __future__ import annotations

import functools
import io
import json

import numpy as np
import pytest

from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.client import Client, ServiceError
from flatserve.errors import InvalidInputError
from flatserve.flats import Flats
from flatserve.grassmann import ICOSAHEDRON_AXES
from flatserve.service.status import LimitExceededError
from tests.harness.fields import ONE_CHART, SINGLE, add_rays
from tests.harness.service import started

C = 2
#: A request written before the top-level ``oriented``: still accepted.
ATLAS = {"kind": "atlas", "atlas": "covering", "oriented": False}
#: How an atlas spec is stored and described (``oriented`` is the field's).
COVERING = {"kind": "atlas", "atlas": "covering"}


@pytest.fixture(autouse=True)
def verbose_descriptions(monkeypatch):
    """These tests read every chart: the client's creates and describes ask for them
    (``verbose=true``; the default answer is a summary)."""
    for name in ("create_field", "describe"):
        monkeypatch.setattr(Client, name,
                            functools.partialmethod(getattr(Client, name), verbose=True))


def sphere_rays(rng, n, spread=1.0):
    """Origins in a cube, directions uniform on the sphere (every orientation)."""
    o = rng.uniform(-spread, spread, (n, 3))
    v = rng.normal(size=(n, 3))
    return o, v / np.linalg.norm(v, axis=1, keepdims=True)


def line_values(o, v):
    """A smooth function of the line (not of the ray's orientation), (n, C)."""
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    p = o - np.einsum("ni,ni->n", o, u)[:, None] * u  # the point closest to the origin
    return np.c_[p[:, 0] + u[:, 2] ** 2, np.sin(p[:, 1]) + u[:, 0] * u[:, 1]]


def same_answers(c, name, probe, want):
    """The field's answers at ``probe`` (.npy and JSON responses) equal ``want``'s."""
    for binary in (True, False):
        got = c.query_rays(name, *probe, binary=binary)
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_array_equal(got.status, want.status)
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-12, equal_nan=True)


def test_covering_atlas_field_accepts_every_orientation_and_restores(make_app, rng, tmp_path):
    batches = [sphere_rays(rng, 700) for _ in range(4)]
    batches = [(o, v, line_values(o, v)) for o, v in batches]
    probe = sphere_rays(rng, 400, spread=0.5)
    ref = AtlasField(Atlas.covering(1, 3, unit="fit"), channels=C)  # (no unit: fitted)

    tc, c = started(make_app())
    try:
        info = c.create_field("a", channels=C, basis=ATLAS)
        assert info["basis"]["spec"] == COVERING and info["oriented"] is False
        assert len(info["charts"]) == ref.atlas.ncharts == 16
        assert [ch["samples"] for ch in info["charts"]] == [0] * 16
        np.testing.assert_array_equal([ch["center"]["A"] for ch in info["charts"]],
                                      ref.atlas.center_A)
        assert info["atlas"]["oriented"] is False
        assert info["atlas"]["covering_radius"] < info["atlas"]["trusted"]
        b = c.create_field("b", channels=C)  # the default (never snapshotted)
        assert b["basis"]["spec"] == COVERING and b["oriented"] is False
        assert b["atlas"] == info["atlas"] and b["charts"] == info["charts"]
        c.create_field("one", channels=C, basis=ONE_CHART)  # the paper's one chart
        for i, (o, v, val) in enumerate(batches):
            ref.add(Flats.from_rays(o, v), val)
            for name in ("a", "b"):
                rep = c.upload_rays(name, o, v, val, binary=bool(i % 2),
                                    idempotency_key=f"k{i}", wait=i != 2)
                assert rep["accepted"] == len(o) and rep["rejected"] == [], rep
                if i == 2:  # acknowledged once stored and charted, inserted later
                    assert not rep["indexed"] and rep["duplicates"] is None
            one = c.upload_rays("one", o, v, val)
            assert one["accepted"] < 0.5 * len(o)  # the single chart refuses most of them
            if i == 1:
                snap = c.snapshot("a")
                assert snap["batch"] == 2
        # wait=false (batch 3): acknowledged unindexed, then indexed in the background
        again = c.upload_rays("a", *batches[2][:2], batches[2][2], idempotency_key="k2",
                              wait=False)
        assert again["replayed"] and again["batch"] == 3
        for name in ("a", "b"):
            info = c.wait_indexed(name, timeout=60)
            assert info["indexed_batch"] == 4 and info["pending_samples"] == 0
            assert info["nsamples"] == ref.nsamples and info["nrejected"] == 0
            assert info["nvertices"] == ref.nstored and info["nsimplex"] == ref.nsimplex
            assert [ch["samples"] for ch in info["charts"]] == ref.samples_per_chart
            assert info["atlas"]["duplication"] == pytest.approx(ref.duplication)
        want = ref.query(Flats.from_rays(*probe))
        assert want.inside.mean() > 0.9
        for name in ("a", "b"):
            same_answers(c, name, probe, want)
        r = tc.post("/v1/fields/a/query?weights=true",
                    json={"origins": probe[0][:3].tolist(), "directions": probe[1][:3].tolist()})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "weights"], \
            r.text
        assert "tangent_simplex" in r.json()["detail"][0]["msg"]  # what to do instead
    finally:
        tc.__exit__(None, None, None)

    # restart: "a" from its snapshot (after batch 2) plus batches 3-4, "b" from batches
    snaps = list((tmp_path / "data" / "snapshots").glob("*.snap"))
    assert len(snaps) == 1 and snaps[0].is_file()  # one file per snapshot, as for one chart
    tc, c = started(make_app())
    try:
        a, b = c.describe("a"), c.describe("b")
        assert a["storage"]["snapshot_batch"] == 2 and b["storage"]["snapshot_batch"] == 0
        for info in (a, b):
            assert info["state"] == "ready" and info["indexed_batch"] == 4
            assert info["nsamples"] == ref.nsamples and info["nvertices"] == ref.nstored
            assert [ch["samples"] for ch in info["charts"]] == ref.samples_per_chart
        for name in ("a", "b"):
            same_answers(c, name, probe, want)
        # a snapshot of the restored field reads back to the same answers
        assert c.snapshot("b")["batch"] == 4
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        assert c.describe("b")["storage"]["snapshot_batch"] == 4
        same_answers(c, "b", probe, want)
    finally:
        tc.__exit__(None, None, None)


def test_oriented_atlas_field_takes_rays_only(api, rng):
    tc, c = api
    info = c.create_field("o", channels=C, basis={"kind": "atlas", "oriented": True})
    assert info["atlas"]["oriented"] is True and len(info["charts"]) == 32
    A = np.array([ch["center"]["A"] for ch in info["charts"]])[:, :, 0]
    np.testing.assert_allclose(A[16:], -A[:16])  # each direction hemisphere its own charts
    o, v = sphere_rays(rng, 1500)
    val = np.c_[v[:, 2], o[:, 0]]  # changes sign with the ray's direction
    rep = c.upload_rays("o", o, v, val)
    assert rep["accepted"] == len(o) and rep["rejected"] == []
    # a ray and its reverse are different samples: each keeps its own value
    o2, v2 = o[:200], v[:200]
    c.upload_rays("o", o2, -v2, np.c_[-v2[:, 2], o2[:, 0]])
    got = c.query_rays("o", np.r_[o2, o2], np.r_[v2, -v2])
    np.testing.assert_allclose(got.values[:, 0], np.r_[v2[:, 2], -v2[:, 2]], atol=1e-9)

    # forms without orientation: 422 naming the array, refused before anything is stored
    f = Flats.from_rays(o[:5], v[:5])
    Q, r = f.quadrics()
    Ap = v[:5, :, None]
    for kw, arr in (({"Q": Q, "r": r}, "Q"), ({"A": Ap, "b": o[:5]}, "A")):
        for binary in (True, False):
            with pytest.raises(InvalidInputError) as ei:
                c.upload("o", val[:5], binary=binary, **kw)
            assert ei.value.status == 422
            assert ei.value.detail[0]["loc"] == ["body", arr], ei.value.detail
            assert "oriented" in ei.value.detail[0]["msg"]
        with pytest.raises(InvalidInputError) as ei:
            c.query("o", **kw)
        assert ei.value.status == 422 and ei.value.detail[0]["loc"] == ["body", arr]
    assert len(c.batches("o")) == 2

    # oriented is for lines only
    r = tc.post("/v1/fields", json={"name": "p", "k": 2, "d": 3,
                                    "basis": {"kind": "atlas", "oriented": True}})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "basis", "oriented"]


def test_oriented_is_a_member_of_the_field(api, rng):
    """`oriented` at the top level (the default atlas of rays); `basis.oriented` of
    older requests still works when it agrees; single charts and k != 1 refuse it."""
    tc, c = api
    new = c.create_field("new", oriented=True)  # no basis: a covering atlas of rays
    old = c.create_field("old", basis={"kind": "atlas", "oriented": True})
    both = c.create_field("both", oriented=True, basis={"kind": "atlas", "oriented": True})
    for info in (new, old, both):
        assert info["oriented"] is True and info["atlas"]["oriented"] is True
        assert info["basis"]["spec"] == COVERING and len(info["charts"]) == 32
        assert info["charts"] == new["charts"]
    assert [f["oriented"] for f in c.list_fields()] == [True] * 3
    o, v = sphere_rays(rng, 50)
    Q, r = Flats.from_rays(o, v).quadrics()
    with pytest.raises(InvalidInputError) as ei:  # oriented: rays only
        c.upload("new", o[:, :1], Q=Q, r=r)
    assert ei.value.detail[0]["loc"] == ["body", "Q"] and "oriented" in str(ei.value)
    plain = c.create_field("plain", oriented=False)
    assert plain["oriented"] is False and len(plain["charts"]) == 16
    assert c.upload("plain", o[:, :1], Q=Q, r=r)["accepted"] == len(o)

    def refused(body, loc, *words):
        r = tc.post("/v1/fields", json={"name": "x", **body})
        assert r.status_code == 422, (body, r.text)
        det = r.json()["detail"][0]
        assert det["loc"] == ["body", *loc], (body, det)
        assert all(w in det["msg"] for w in words), (body, det)

    refused({"oriented": True, "basis": {"kind": "atlas", "oriented": False}}, ["oriented"],
            "disagree")
    refused({"oriented": False, "basis": {"kind": "atlas", "oriented": True}}, ["oriented"],
            "disagree")
    refused({"k": 2, "oriented": True}, ["oriented"], "k = 1")
    refused({"k": 2, "basis": {"kind": "atlas", "oriented": True}}, ["basis", "oriented"],
            "k = 1")
    for one in ({"kind": "tangent_simplex"}, {"scale": 0.1}):
        refused({"oriented": True, "basis": one}, ["oriented"], "single chart")
    refused({"oriented": "yes"}, ["oriented"])
    assert {f["name"] for f in c.list_fields()} == {"new", "old", "both", "plain"}


def test_atlas_spec_is_strict_and_fields_only(api):
    tc, _ = api
    for basis in ({"kind": "atlas", "atlas": "data"}, {"kind": "atlas", "scale": 0.1},
                  {"kind": "atlas", "oriented": "yes"}):
        r = tc.post("/v1/fields", json={"name": "x", "basis": basis})
        assert r.status_code == 422, (basis, r.text)
        assert r.json()["detail"][0]["loc"][:3] == ["body", "basis", "atlas"], r.text
    # the stateless coordinates route charts in one basis: no atlas there
    r = tc.post("/v1/math/coordinates", json={"basis": {"kind": "atlas"},
                                              "flats": {"origins": [[0, 0, 0]],
                                                        "directions": [[0, 0, 1]]}})
    assert r.status_code == 422, r.text
    assert tc.get("/v1/fields").json()["fields"] == []


def test_atlas_fields_for_other_dimensions(api, rng):
    """Planes in R^4 and points: every orientation accepted (one chart takes a part)."""
    tc, c = api
    info = c.create_field("p", k=2, d=4, basis={"kind": "atlas"})
    n = 300
    A = np.linalg.qr(rng.normal(size=(n, 4, 2)))[0]
    b = rng.uniform(-1, 1, (n, 4))
    rep = c.upload("p", b[:, :1], A=A, b=b)
    assert rep["accepted"] == n and len(info["charts"]) == Atlas.covering(2, 4).ncharts
    dflt = c.create_field("dflt", k=2, d=4)  # without basis: the same covering atlas
    assert dflt["charts"] == info["charts"] and dflt["basis"]["spec"] == COVERING
    assert c.upload("dflt", b[:, :1], A=A, b=b)["accepted"] == n
    one = c.create_field("q", k=2, d=4, basis=ONE_CHART)
    assert one.get("charts") is None and one.get("atlas") is None  # one chart: `basis`
    assert c.upload("q", b[:, :1], A=A, b=b)["accepted"] < n
    for basis in ({"kind": "atlas"}, None):  # points have no orientation: one chart
        pts = c.create_field(f"pts{basis is None}", k=0, d=3, basis=basis)
        assert len(pts["charts"]) == 1


def test_render_an_oriented_atlas_field(api, rng):
    tc, c = api
    c.create_field("lf", basis={"kind": "atlas", "oriented": True})
    # origins spread over the region the views' rays pass through (a narrow chart's
    # hull holds no ray that passes far from every sample)
    o, v = sphere_rays(rng, 3000, spread=1.5)
    c.upload_rays("lf", o, v, (v[:, 2] > 0).astype(float))
    means = []
    for yaw in (0.0, 180.0):  # eyes on both sides: rays of opposite hemispheres
        r = tc.post("/v1/fields/lf/render", json={"orbit": {"yaw": yaw}, "width": 16,
                                                  "height": 16, "supersample": 1,
                                                  "format": "npy"})
        assert r.status_code == 200, r.text
        assert float(r.headers["X-Coverage"]) > 0.5
        img = np.load(io.BytesIO(r.content))
        means.append(float(np.nanmean(img)))
    # the eye at -z sees the rays going +z (value 1), the eye at +z those going -z (0)
    assert means[0] > 0.95 and means[1] < 0.05, means


def cone(rng, n, axis, half_deg):
    """``n`` unit directions uniform in angle within ``half_deg`` of ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    w = rng.normal(size=(n, 3))
    w -= (w @ a)[:, None] * a
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    t = np.radians(half_deg) * np.sqrt(rng.uniform(size=n))
    return np.cos(t)[:, None] * a + np.sin(t)[:, None] * w


def test_samples_atlas_charts_where_the_flats_are(make_app, rng):
    """`atlas: "samples"`: the library's Atlas.for_samples of the given flats (any form),
    described chart by chart, stored with the field; a later flat that no chart holds is
    rejected with its reason; the number of flats is bounded."""
    n = 1500
    v = cone(rng, n, [1, 0.3, 0], 40)
    o = rng.uniform(-2, 2, (n, 3)) + [5, 0, 0]
    val = np.c_[o[:, 1], v[:, 2]]
    flats = Flats.from_rays(o, v)
    ref = AtlasField(Atlas.for_samples(flats, unit="fit"), channels=C)
    assert ref.atlas.ncharts > 1
    A, b = v[:, :, None], o
    tc, c = started(make_app(max_atlas_samples=n))
    try:
        spec = {"kind": "atlas", "atlas": "samples",
                "samples": {"origins": o.tolist(), "directions": v.tolist()}}
        info = c.create_field("s", channels=C, basis=spec)
        assert info["basis"]["spec"] == {"kind": "atlas", "atlas": "samples", "radius": 30.0,
                                         "fraction": 0.99, "samples": {"form": "rays", "n": n}}
        assert info["atlas"]["method"] == "samples" and info["atlas"]["covering_radius"] is None
        assert info["atlas"]["max_sample_angle"] == ref.atlas.info["max_sample_angle_deg"] < 30
        assert len(info["charts"]) == ref.atlas.ncharts
        np.testing.assert_array_equal([ch["center"]["A"] for ch in info["charts"]],
                                      ref.atlas.center_A)
        np.testing.assert_array_equal([ch["center"]["r"] for ch in info["charts"]],
                                      ref.atlas.center_r)
        assert [ch["scale"] for ch in info["charts"]] == ref.atlas.scales.tolist()
        # the same flats as (A, b): the same atlas
        par = c.create_field("p", channels=C, basis={
            "kind": "atlas", "atlas": "samples", "samples": {"A": A.tolist(), "b": b.tolist()}})
        assert len(par["charts"]) == len(info["charts"])
        for key in ("A", "r"):  # (to rounding: the forms give the same flats)
            np.testing.assert_allclose([ch["center"][key] for ch in par["charts"]],
                                       [ch["center"][key] for ch in info["charts"]],
                                       rtol=1e-9, atol=1e-12)
        # (not the scales: the bisection's answer moves with rounding, the fraction of
        # flats inside each simplex it reaches does not)

        rep = c.upload_rays("s", o, v, val)
        ref.add(flats, val)
        assert rep["accepted"] == n and rep["rejected"] == []
        got = c.describe("s")
        assert [ch["samples"] for ch in got["charts"]] == ref.samples_per_chart
        assert got["nvertices"] == ref.nstored and got["nsimplex"] == ref.nsimplex
        # lines across the cone (45 degrees and more from every centre): no chart holds them
        o2 = rng.uniform(-1, 1, (40, 3))
        v2 = cone(rng, 40, [0, 0, 1], 5)
        late = c.upload_rays("s", o2, v2, np.ones((40, C)))
        assert late["accepted"] == 0 and late["rejected"] == list(range(40))
        want_reasons = ref.prepare(Flats.from_rays(o2, v2), np.ones((40, C))).reasons
        assert late["reasons"] == want_reasons
        assert all("outside every chart's domain" in why for why in late["reasons"])
        probe = (o[:300] + rng.normal(0, 0.05, (300, 3)), v[:300])
        want = ref.query(Flats.from_rays(*probe))
        # most probes answered (those beside samples on the cloud's edge may leave the hull)
        assert want.inside.mean() > 0.8
        same_answers(c, "s", probe, want)
        outside = c.query_rays("s", o2, v2)
        assert not outside.inside.any() and np.isnan(outside.values).all()
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app(max_atlas_samples=n))  # restart: the atlas is stored with it
    try:
        assert c.describe("s")["charts"] == got["charts"]
        same_answers(c, "s", probe, want)
        # bounded: one flat more than max_atlas_samples is a 413 naming the setting
        big = np.zeros((n + 1, 3)).tolist()
        r = tc.post("/v1/fields", json={"name": "big", "basis": {
            "kind": "atlas", "atlas": "samples", "samples": {"origins": big, "directions": big}}})
        assert r.status_code == 413 and "FLATSERVE_MAX_ATLAS_SAMPLES" in r.text, r.text
        assert "basis.samples" in r.text
        assert sorted(f["name"] for f in c.list_fields()) == ["p", "s"]
    finally:
        tc.__exit__(None, None, None)


def test_atlas_specs_that_do_not_cover_what_they_claim_are_refused(api, rng):
    """At creation, a 422 naming what is not covered: an orientation too far from every
    centre, a chart whose scale collapses it, flats the data-driven atlas cannot chart;
    oriented fields take rays only, in the spec too."""
    tc, c = api

    def refused(basis, loc, *words, **top):
        r = tc.post("/v1/fields", json={"name": "x", "basis": basis, **top})
        assert r.status_code == 422, r.text
        det = r.json()["detail"][0]
        assert det["loc"] == ["body", *loc], det
        assert all(w in det["msg"] for w in words), det
        return det["msg"]

    def centers(axes, **kw):
        return {"kind": "atlas", "atlas": "centers",
                "centers": {"origins": np.zeros((len(axes), 3)).tolist(),
                            "directions": np.asarray(axes).tolist()}, **kw}

    # the 3 coordinate axes leave directions 54.7 degrees from every centre
    msg = refused(centers(np.eye(3)), ["basis", "centers"], "do not cover every orientation",
                  "degrees from every centre", "trusted 40")
    worst = float(msg.split(" is ")[1].split(" degrees")[0])
    assert 50 < worst <= np.degrees(np.arccos(1 / np.sqrt(3))) + 1e-6
    # the 6 icosahedral axes cover (37.4 degrees), unless a scale collapses a chart
    ico = ICOSAHEDRON_AXES
    info = c.create_field("ico", basis=centers(ico))
    assert info["atlas"]["method"] == "centers" and len(info["charts"]) == 6
    assert 37 < info["atlas"]["covering_radius"] < 38
    got = np.array([ch["center"]["A"] for ch in info["charts"]])[:, :, 0]
    np.testing.assert_allclose(np.abs(np.einsum("ci,ci->c", got, ico)), 1.0)  # the same lines
    refused(centers(ico, scale=1e-12), ["basis", "centers"], "chart 0", "scale 1e-12")
    refused(centers(ico, scale=[1.0] * 5), ["basis", "scale"], "one per centre")
    refused(centers(np.tile(ico, (200, 1))), ["basis", "centers"], "1200 flats", "at most")
    refused(centers(ico, scale=0), ["basis", "atlas", "centers", "scale", "constrained-float"],
            "greater than 0")
    # flats the data-driven atlas cannot chart (offsets far beyond what a scale holds in
    # the unit 1; a unit from the data, the default, would be their own size)
    v = cone(rng, 200, [1, 0, 0], 20)
    o = rng.uniform(-1e6, 1e6, (200, 3))
    refused({"kind": "atlas", "atlas": "samples",
             "samples": {"origins": o.tolist(), "directions": v.tolist()}},
            ["basis", "samples"], "does not chart", "not representable", unit=1.0)
    # oriented: centres and samples must be rays; (Q, r) has no orientation
    Q, r = Flats.from_rays(np.zeros((6, 3)), ico).quadrics()
    refused({"kind": "atlas", "atlas": "centers", "centers": {"Q": Q.tolist(), "r": r.tolist()}},
            ["basis", "centers"], "rays", oriented=True)
    refused({"kind": "atlas", "atlas": "samples", "samples": {"Q": Q.tolist(), "r": r.tolist()}},
            ["basis", "samples", "Q"], "oriented", "origins + directions", oriented=True)
    refused({"kind": "atlas", "atlas": "samples",
             "samples": {"origins": [[0, 0, 0]], "directions": [[0, 0, 0]]}},
            ["basis", "samples", "directions"])
    assert [f["name"] for f in c.list_fields()] == ["ico"]


def test_cost_guard_counts_every_chart_holding_a_sample(make_app, rng):
    """An atlas stores a sample in every chart whose domain holds it: the limit on cells
    is judged on those copies (lines in R^4: about 2.4 charts hold each)."""
    n = 300
    o, v = rng.uniform(-1, 1, (n, 4)), rng.normal(size=(n, 4))
    flats = Flats.from_rays(o, v)
    atlas = Atlas.covering(1, 4)
    copies = atlas.held(flats, atlas.reach).sum()
    assert copies > 2 * n
    per = 512.0  # cells per sample in dimension 6 before a field has its own figure
    limit = int(1.5 * n * per)  # above n samples' cells, below the copies'
    tc, c = started(make_app(max_simplices=limit, min_field_samples=0))  # the upload guard
    try:
        c.create_field("a", k=1, d=4)
        c.create_field("one", k=1, d=4, basis=ONE_CHART)
        with pytest.raises(LimitExceededError) as ei:
            c.upload_rays("a", o, v, np.ones(n))
        assert ei.value.status == 413
        text = str(ei.value)
        assert f"{copies * per:,.0f} cells expected" in text and "charts holding each" in text
        assert "FLATSERVE_MAX_SIMPLICES" in text and c.describe("a")["storage"]["batches"] == 0
        assert c.upload_rays("one", o, v, np.ones(n))["accepted"] > 0  # one copy each
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app(max_simplices=int(copies * per) + 1, min_field_samples=0))
    try:
        assert c.upload_rays("a", o, v, np.ones(n))["accepted"] == n
        info = c.describe("a")  # the copies counted are the vertices the charts hold
        assert info["nvertices"] == copies
        assert sum(ch["samples"] for ch in info["charts"]) == copies
    finally:
        tc.__exit__(None, None, None)


def test_unit_of_length_is_validated_stored_and_restored(make_app, rng):
    """``unit`` (top level, atlas fields only): the charts' unit of length; the
    answers are the library's atlas of that unit, before and after a restart."""
    o, v = sphere_rays(rng, 1500, spread=0.5)
    val = line_values(o, v)
    probe = sphere_rays(rng, 300, spread=0.4)
    ref = AtlasField(Atlas.covering(1, 3, oriented=True, unit=0.4), channels=C)
    ref.add(Flats.from_rays(o, v), val)
    want = ref.query(Flats.from_rays(*probe))
    assert want.inside.mean() > 0.5
    plain = AtlasField(Atlas.covering(1, 3, oriented=True), channels=C)
    plain.add(Flats.from_rays(o, v), val)
    assert not np.allclose(plain.query(Flats.from_rays(*probe)).values, want.values,
                           equal_nan=True)  # the unit changes the answers
    tc, c = started(make_app())
    try:
        info = c.create_field("u", channels=C, oriented=True, unit=0.4)  # no basis
        assert info["atlas"]["unit"] == 0.4 and len(info["charts"]) == 32
        assert info["atlas"]["unit_from"] == "given"
        dflt = c.create_field("one", channels=C)["atlas"]  # the default: fitted to the first batch
        assert dflt["unit"] is None and dflt["unit_from"] == "fit"
        c.upload_rays("u", o, v, val)
        same_answers(c, "u", probe, want)
        for body, words in (({"unit": 0}, ()), ({"unit": -1.0}, ()), ({"unit": "x"}, ()),
                            ({"unit": 0.5, "basis": {"kind": "tangent_simplex"}},
                             ("single chart", "atlas"))):
            r = tc.post("/v1/fields", json={"name": "x", **body})
            assert r.status_code == 422, (body, r.text)
            det = r.json()["detail"][0]
            assert det["loc"][-1] == "unit" and all(w in det["msg"] for w in words), det
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        assert c.describe("u")["atlas"]["unit"] == 0.4
        same_answers(c, "u", probe, want)
    finally:
        tc.__exit__(None, None, None)


def test_reach_of_a_covering_atlas_is_validated_stored_and_restored(make_app, rng):
    """``basis.reach`` of a covering atlas: samples stored in every chart closer than
    it (more duplication, the library's atlas of that reach), kept across a restart;
    a reach that breaks ``trusted <= reach < 45`` is a 422 naming ``reach``."""
    o, v = sphere_rays(rng, 1500, spread=0.5)
    val = line_values(o, v)
    probe = sphere_rays(rng, 300, spread=0.4)
    ref = AtlasField(Atlas.covering(1, 3, oriented=True, reach=35.0, unit="fit"), channels=C)
    ref.add(Flats.from_rays(o, v), val)
    want = ref.query(Flats.from_rays(*probe))
    tc, c = started(make_app())
    try:
        info = c.create_field("r", channels=C, oriented=True,
                              basis={"kind": "atlas", "atlas": "covering", "reach": 35})
        assert info["atlas"]["reach"] == 35.0 and info["basis"]["spec"]["reach"] == 35.0
        default = c.create_field("d", channels=C, oriented=True)
        assert default["atlas"]["reach"] == 27.0 and "reach" not in default["basis"]["spec"]
        c.upload_rays("r", o, v, val)
        c.upload_rays("d", o, v, val)
        wide, narrow = c.describe("r")["atlas"], c.describe("d")["atlas"]
        assert wide["nstored"] == ref.nstored and wide["duplication"] > narrow["duplication"]
        same_answers(c, "r", probe, want)
        for reach, words in ((20, ("reach", "trusted=24")), (45, ()), (0, ()), ("x", ())):
            r = tc.post("/v1/fields", json={"name": "x", "basis": {
                "kind": "atlas", "atlas": "covering", "reach": reach}})
            assert r.status_code == 422, (reach, r.text)
            det = r.json()["detail"][0]
            assert det["loc"][-1] == "reach" or "reach" in det["loc"], det
            assert all(w in det["msg"] for w in words), det
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        assert c.describe("r")["atlas"]["reach"] == 35.0
        same_answers(c, "r", probe, want)
    finally:
        tc.__exit__(None, None, None)


def test_a_field_stored_before_isometric_charts_restores_as_it_was_built(make_app, rng,
                                                                        tmp_path):
    """A stored atlas spec without ``isometric`` (written before charts could be warped)
    comes back with the paper's charts: its answers are the library's unwarped atlas's,
    and describe says so; a new field's charts are isometric."""
    import json
    import sqlite3

    from flatserve.service.log.storage import DB_NAME

    o, v = sphere_rays(rng, 1500, spread=0.5)
    val = line_values(o, v)
    probe = sphere_rays(rng, 300, spread=0.4)
    paper = AtlasField(Atlas.covering(1, 3, oriented=True, isometric=False, unit=1.0),
                       channels=C)  # (unit 1: what an earlier version stored)
    paper.add(Flats.from_rays(o, v), val)
    iso = AtlasField(Atlas.covering(1, 3, oriented=True, unit="fit"), channels=C)
    iso.add(Flats.from_rays(o, v), val)
    want_paper = paper.query(Flats.from_rays(*probe))
    assert not np.allclose(iso.query(Flats.from_rays(*probe)).values, want_paper.values,
                           equal_nan=True)  # the warp changes the answers
    tc, c = started(make_app())
    try:
        assert c.create_field("old", channels=C, oriented=True)["atlas"]["isometric"] is True
        c.upload_rays("old", o, v, val)
        same_answers(c, "old", probe, iso.query(Flats.from_rays(*probe)))
    finally:
        tc.__exit__(None, None, None)
    db = sqlite3.connect(tmp_path / "data" / DB_NAME)
    (spec,) = db.execute("SELECT spec FROM fields WHERE name = 'old'").fetchone()
    spec = json.loads(spec)
    del spec["atlas"]["isometric"]  # as an earlier version stored it (unit 1 then)
    del spec["atlas"]["unit_from_data"], spec["atlas"]["unit_rule"]
    db.execute("UPDATE fields SET spec = ? WHERE name = 'old'", (json.dumps(spec),))
    db.commit()
    db.close()
    tc, c = started(make_app())
    try:
        assert c.describe("old")["atlas"]["isometric"] is False
        same_answers(c, "old", probe, want_paper)
    finally:
        tc.__exit__(None, None, None)


def test_a_first_batch_of_one_flat_gives_the_default_unit_and_later_batches_keep_it(api, rng):
    """One flat has no spread and is too few to fit a unit to: data_unit is 1
    (DEFAULT_UNIT), taken from the first batch (inserted through this replica's own
    hand-over) and kept by the next; the rule is still described as ``fit``."""
    from flatserve.atlas import DEFAULT_UNIT

    tc, c = api
    c.create_field("one", channels=C)
    c.upload_rays("one", [[0.1, 0.2, -3.0]], [[0, 0, 1.0]], [[0.5, 0.5]])
    assert c.describe("one")["atlas"]["unit"] == DEFAULT_UNIT
    o, v = sphere_rays(rng, 2000, spread=3.0)
    assert c.upload_rays("one", o, v, line_values(o, v))["accepted"] == 2000
    got = c.describe("one")["atlas"]
    assert got["unit"] == DEFAULT_UNIT and got["unit_from"] == "fit"


def test_a_unit_from_the_data_is_chosen_once_and_recorded_with_the_batches(make_app, rng,
                                                                         monkeypatch):
    """A field created with ``unit: "data"`` takes data_unit of its first batch; the unit
    is stored with the batches, so a restart (from the log, then from a snapshot) and
    an import get it from storage, not by choosing again: with the estimator
    replaced by another answer meanwhile they still have the recorded unit."""
    import flatserve.atlas_field
    from flatserve.atlas import data_unit

    batches = []
    for _ in range(2):
        o, v = sphere_rays(rng, 900, spread=2.0)
        batches.append((o, v, line_values(o, v)))
    probe = sphere_rays(rng, 300, spread=1.5)
    u = data_unit(Flats.from_rays(*batches[0][:2]), batches[0][2])
    assert abs(u - 1.0) > 0.2  # not the former default
    ref = AtlasField(Atlas.covering(1, 3, oriented=True, unit=None), channels=C)
    for o, v, val in batches:
        ref.add(Flats.from_rays(o, v), val)
    assert ref.atlas.unit == u
    want = ref.query(Flats.from_rays(*probe))
    tc, c = started(make_app())
    try:
        info = c.create_field("auto", channels=C, oriented=True, unit="data")
        assert info["atlas"]["unit"] is None and info["atlas"]["unit_from"] == "data"
        for o, v, val in batches:
            c.upload_rays("auto", o, v, val)
        got = c.describe("auto")["atlas"]
        assert got["unit"] == u and got["unit_from"] == "data"
        same_answers(c, "auto", probe, want)
        export = c.export_field("auto")
    finally:
        tc.__exit__(None, None, None)

    def other(*a, **kw):
        return 5.0

    monkeypatch.setattr(flatserve.atlas_field, "data_unit", other)  # (the upload room's too)
    for snapshot in (False, True):  # restored from the log, then from a snapshot
        tc, c = started(make_app())
        try:
            assert c.describe("auto")["atlas"]["unit"] == u
            same_answers(c, "auto", probe, want)
            if snapshot:
                c.import_field("copy", export)
                assert c.describe("copy")["atlas"]["unit"] == u
                same_answers(c, "copy", probe, want)
                fresh = c.create_field("fresh", channels=C, oriented=True, unit="data")["atlas"]
                assert fresh["unit"] is None
                c.upload_rays("fresh", *batches[0])
                assert c.describe("fresh")["atlas"]["unit"] == 5.0  # the estimator's answer
            else:
                c.snapshot("auto")
        finally:
            tc.__exit__(None, None, None)


def test_a_unit_fitted_to_the_first_batch_over_http(make_app, rng, monkeypatch):
    """``unit: "fit"``: the field takes the library's fitted unit of its first batch
    (not the geometry's), answers as the library's field, describes it as ``fit``
    and keeps it after a restart (recorded with the batch: the fit replaced by
    another answer meanwhile changes nothing); a field created without ``unit``
    does the same up to R^4, and takes the geometry's unit beyond; ``"data"``
    takes the geometry's unit; another word is a 422 naming ``unit``."""
    import flatserve.atlas_field
    from flatserve.atlas import data_unit
    from flatserve.atlas_field import FittedUnit

    o, v = sphere_rays(rng, 1500, spread=2.0)
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    val = np.stack([np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1])] * C, axis=1)
    probe = sphere_rays(rng, 300, spread=1.5)
    lib = AtlasField(Atlas.covering(1, 3, oriented=True, unit="fit"), channels=C)
    lib.add(Flats.from_rays(o, v), val)
    u = lib.atlas.unit
    assert u > 1.5 * data_unit(Flats.from_rays(o, v), val)
    want = lib.query(Flats.from_rays(*probe))
    tc, c = started(make_app())
    try:
        info = c.create_field("fit", channels=C, oriented=True, unit="fit")
        assert info["atlas"]["unit"] is None and info["atlas"]["unit_from"] == "fit"
        assert c.create_field("said", channels=C, unit="data")["atlas"]["unit_from"] == "data"
        left = c.create_field("left", channels=C, oriented=True)["atlas"]  # unit left out
        assert left["unit"] is None and left["unit_from"] == "fit"
        # beyond 6 chart dimensions (lines in R^5: 8) a fit costs minutes: left out,
        # the geometry's unit
        assert c.create_field("r5", k=1, d=5)["atlas"]["unit_from"] == "data"
        assert c.create_field("r5fit", k=1, d=5, unit="fit")["atlas"]["unit_from"] == "fit"
        # points: a uniform scale cannot change their cells, a fit only costs time
        assert c.create_field("p6", k=0, d=6)["atlas"]["unit_from"] == "data"
        r = tc.post("/v1/fields", json={"name": "bad", "k": 1, "d": 3, "unit": "fitted"})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "unit", r.text
        # an atlas for given flats whose unit is fit: its charts checked in the
        # geometry's unit at create, the unit fitted to the first batch
        fs = c.create_field("fs", channels=C, oriented=True, unit="fit", basis={
            "kind": "atlas", "atlas": "samples",
            "samples": {"origins": o[:400].tolist(), "directions": v[:400].tolist()}})
        assert fs["atlas"]["unit_from"] == "fit" and fs["atlas"]["unit"] is None
        c.upload_rays("fs", o[:400], v[:400], val[:400])
        assert c.describe("fs")["atlas"]["unit_from"] == "fit"
        c.upload_rays("fit", o, v, val)
        got = c.describe("fit")["atlas"]
        assert got["unit"] == u and got["unit_from"] == "fit"
        same_answers(c, "fit", probe, want)
        c.upload_rays("left", o, v, val)
        assert c.describe("left")["atlas"] == got
        same_answers(c, "left", probe, want)
        c.upload_rays("said", o, v, val)
        assert c.describe("said")["atlas"]["unit"] == data_unit(Flats.from_rays(o, v), val)
    finally:
        tc.__exit__(None, None, None)
    monkeypatch.setattr(flatserve.atlas_field, "fitted_unit", lambda *a, **kw: FittedUnit(
        5.0, np.array([5.0]), np.array([0.0]), 1))  # (a restart that fitted again: unit 5)
    tc, c = started(make_app())
    try:
        got = c.describe("fit")["atlas"]
        assert got["unit"] == u and got["unit_from"] == "fit"
        same_answers(c, "fit", probe, want)
    finally:
        tc.__exit__(None, None, None)


def test_a_covering_atlas_takes_its_radii_at_create(api, rng):
    """``inner`` and ``trusted`` beside ``reach``: hyperplanes in R^4 with narrower
    relative radii (1, 4, 9) store fewer copies than the default's (2, 6, 14) and
    answer the library's atlas of those radii; radii out of order, or a trusted
    radius the covering does not fit in, are 422s naming the radius."""
    from flatserve.grassmann import haar_frames

    tc, c = api
    A = haar_frames(1500, 4, 3, rng)
    b = rng.uniform(-1, 1, (1500, 4))
    val = np.sin(3 * b[:, :1]) + A[:, :1, 0]
    qA, qb = haar_frames(300, 4, 3, rng), rng.uniform(-1, 1, (300, 4))
    lib = AtlasField(Atlas.covering(3, 4, relative=True, inner=1, trusted=4, reach=9, unit=1.0),
                     channels=1)
    lib.add(Flats.from_parametric(A, b), val)
    want = lib.query(Flats.from_parametric(qA, qb))
    assert want.inside.mean() > 0.5
    got = c.create_field("narrow", k=3, d=4, unit=1.0, basis={
        "kind": "atlas", "atlas": "covering", "inner": 1, "trusted": 4, "reach": 9})["atlas"]
    assert (got["inner"], got["trusted"], got["reach"], got["relative"]) == (1, 4, 9, True)
    c.create_field("wide", k=3, d=4, unit=1.0)
    for name in ("narrow", "wide"):
        c.upload_parametric(name, A, b, val)
    dup = [c.describe(n)["atlas"]["duplication"] for n in ("narrow", "wide")]
    assert dup[0] < 0.85 * dup[1], dup
    same_parametric(c, "narrow", qA, qb, want)
    for radii, name in (({"inner": 5, "trusted": 4}, "trusted"),
                        ({"trusted": 10, "relative": False}, "trusted"),
                        ({"trusted": 50}, "trusted"),
                        ({"trusted": 8, "reach": 8}, "reach")):  # relative: no seam
        r = tc.post("/v1/fields", json={"name": "bad", "k": 3, "d": 4, "basis": {
            "kind": "atlas", "atlas": "covering", **radii}})
        assert r.status_code == 422, (radii, r.text)
        assert name in json.dumps(r.json()["detail"]), (radii, r.text)


def test_a_thinner_seam_is_taken_at_create_described_and_validated(make_app, rng):
    """Planes in R^4 by default keep a net of their outer seam (beyond 7 degrees, a
    spacing of 1; 59 charts), described, and stored as the library's atlas stores
    them, across a snapshot and a restart between two uploads; ``dense_reach``,
    ``dense_after`` and ``seam_spacing`` given at create are kept; bad ones are 422s
    naming them."""
    import time

    from flatserve.grassmann import haar_frames

    A, b = haar_frames(1200, 4, 2, rng), rng.uniform(-1, 1, (1200, 4))
    val = np.sin(3 * b[:, :1]) + A[:, :1, 0]
    qA, qb = haar_frames(300, 4, 2, rng), rng.uniform(-1, 1, (300, 4))
    lib = AtlasField(Atlas.covering(2, 4, unit=1.0), channels=1)
    lib.add(Flats.from_parametric(A, b), val)
    want = lib.query(Flats.from_parametric(qA, qb))
    tc, c = started(make_app(snapshot_every=500))
    try:
        got = c.create_field("planes", k=2, d=4, unit=1.0)["atlas"]
        assert (got["dense_reach"], got["dense_after"], got["seam_spacing"],
                got["relative"]) == (7.0, None, 1.0, True)
        c.upload_parametric("planes", A[:700], b[:700], val[:700])
        end = time.monotonic() + 60
        while c.describe("planes")["storage"]["snapshot_batch"] < 1:  # the first snapshot
            assert time.monotonic() < end, "no snapshot written"
            time.sleep(0.2)
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        c.upload_parametric("planes", A[700:], b[700:], val[700:])
        info = c.describe("planes", verbose=True)
        assert len(info["charts"]) == 59 and info["atlas"]["nstored"] == lib.nstored
        assert [ch["samples"] for ch in info["charts"]] == [f.nsamples for f in lib.fields]
        same_parametric(c, "planes", qA, qb, want)
        mine = c.create_field("mine", k=3, d=4, unit=1.0, basis={
            "kind": "atlas", "atlas": "covering", "dense_reach": 8, "dense_after": 3})["atlas"]
        assert (mine["dense_reach"], mine["dense_after"], mine["seam_spacing"]) == (8.0, 3, None)
        net = c.create_field("net", k=3, d=4, unit=1.0, basis={
            "kind": "atlas", "atlas": "covering", "dense_reach": 8, "seam_spacing": 0.5,
            "dense_after": 40})["atlas"]
        assert (net["dense_reach"], net["dense_after"], net["seam_spacing"]) == (8.0, 40, 0.5)
        assert c.create_field("lines", k=1, d=4)["atlas"]["dense_reach"] is None
        for given, name in (({"dense_reach": 8}, "dense_after"),
                            ({"dense_after": 3}, "dense_reach"),
                            ({"seam_spacing": 1}, "dense_reach"),
                            ({"dense_reach": 8, "seam_spacing": 0}, "seam_spacing"),
                            ({"dense_reach": 8, "seam_spacing": -2}, "seam_spacing"),
                            ({"dense_reach": 8, "seam_spacing": "x"}, "seam_spacing"),
                            ({"dense_reach": 8, "seam_spacing": 1e9}, "seam_spacing"),
                            ({"dense_reach": 5, "dense_after": 3}, "dense_reach"),
                            ({"dense_reach": 8, "dense_after": -1}, "dense_after"),
                            ({"dense_reach": 8, "dense_after": "3"}, "dense_after"),
                            ({"dense_reach": 8, "dense_after": 3, "relative": False},
                             "dense_reach")):
            r = tc.post("/v1/fields", json={"name": "bad", "k": 3, "d": 4, "basis": {
                "kind": "atlas", "atlas": "covering", **given}})
            assert r.status_code == 422, (given, r.text)
            assert name in json.dumps(r.json()["detail"]), (given, r.text)
    finally:
        tc.__exit__(None, None, None)


def same_parametric(c, name, qA, qb, want):
    """The field's answers at the flats (qA, qb), binary and JSON, are the library's."""
    for binary in (True, False):
        got = c.query_parametric(name, qA, qb, binary=binary)
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-12,
                                   equal_nan=True)


def test_isometric_charts_of_planes_asked_for_at_create_answer_as_the_librarys(make_app, rng):
    """``isometric`` of a covering atlas: planes in R^3 with warped charts
    (flatserve.warp.FlatWarp) answer the library's bits, describe says so, and a
    restart (the stored atlas with its warps) answers the same."""
    from flatserve.grassmann import haar_frames

    A = haar_frames(1500, 3, 2, rng)
    b = rng.uniform(-1, 1, (1500, 3))
    val = np.sin(3 * b[:, :1]) + A[:, :1, 0]
    qA, qb = haar_frames(300, 3, 2, rng), rng.uniform(-1, 1, (300, 3))
    lib = AtlasField(Atlas.covering(2, 3, isometric=True, unit=1.0), channels=1)
    lib.add(Flats.from_parametric(A, b), val)
    want = lib.query(Flats.from_parametric(qA, qb))
    assert want.inside.mean() > 0.8

    def same(c):
        same_parametric(c, "p", qA, qb, want)

    tc, c = started(make_app())
    try:
        d = c.create_field("p", k=2, d=3, unit=1.0,
                           basis={"kind": "atlas", "atlas": "covering", "isometric": True})
        assert d["atlas"]["isometric"] is True
        assert c.create_field("q", k=2, d=3, unit=1.0)["atlas"]["isometric"] is False
        c.upload_parametric("p", A, b, val)
        same(c)
        with pytest.raises(ServiceError) as err:  # points have no warp: named
            c.create_field("pts", k=0, d=3,
                           basis={"kind": "atlas", "atlas": "covering", "isometric": True})
        assert err.value.status == 422 and "isometric" in str(err.value.detail)
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        assert c.describe("p")["atlas"]["isometric"] is True
        same(c)
    finally:
        tc.__exit__(None, None, None)


def test_a_relative_atlas_asked_for_at_create_answers_as_the_librarys(make_app, rng):
    """``relative`` of a covering atlas: lines in R^4 whose charts' radii are measured
    from each line's nearest centre answer the library's bits, store fewer copies
    than balls about the centres (describe's duplication), and a restart answers the
    same; it is the default from R^4 on."""
    from flatserve.grassmann import haar_frames

    A = haar_frames(1500, 4, 1, rng)
    b = rng.uniform(-1, 1, (1500, 4))
    val = np.sin(3 * b[:, :1]) + A[:, :1, 0]
    qA, qb = haar_frames(300, 4, 1, rng), rng.uniform(-1, 1, (300, 4))
    lib = AtlasField(Atlas.covering(1, 4, relative=True, unit=1.0), channels=1)
    lib.add(Flats.from_parametric(A, b), val)
    want = lib.query(Flats.from_parametric(qA, qb))
    assert want.inside.mean() > 0.3

    def same(c):
        same_parametric(c, "r", qA, qb, want)

    tc, c = started(make_app())
    try:
        d = c.create_field("r", k=1, d=4, unit=1.0,
                           basis={"kind": "atlas", "atlas": "covering", "relative": True})
        assert d["atlas"]["relative"] is True and d["atlas"]["reach"] == 14.0
        c.create_field("ball", k=1, d=4, unit=1.0,
                       basis={"kind": "atlas", "atlas": "covering", "relative": False})
        assert c.describe("ball")["atlas"]["relative"] is False
        # the default: relative from R^4 on, balls in R^3
        assert c.create_field("dflt", k=1, d=4)["atlas"]["relative"] is True
        assert c.create_field("l3", k=1, d=3)["atlas"]["relative"] is False
        c.upload_parametric("r", A, b, val)
        c.upload_parametric("ball", A, b, val)
        dup = [c.describe(n)["atlas"]["duplication"] for n in ("r", "ball")]
        assert dup[0] < 2.6 < dup[1]
        same(c)
        with pytest.raises(ServiceError) as err:
            c.create_field("bad", k=1, d=4,
                           basis={"kind": "atlas", "atlas": "covering", "relative": "often"})
        assert err.value.status == 422 and "relative" in str(err.value.detail)
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app())
    try:
        assert c.describe("r")["atlas"]["relative"] is True
        same(c)
    finally:
        tc.__exit__(None, None, None)


def test_the_gradient_interpolant_over_http_answers_as_the_librarys(make_app, rng,
                                                                    monkeypatch):
    """``interpolant=gradient``: planes in R^3 in an atlas field and rays in a one-chart
    field answer the library's ``query(interpolant="gradient")`` (.npy and JSON, a
    large query and a small one, which is not answered on the event loop), not the
    linear answer; an unknown interpolant is a 422 naming it."""
    from flatserve.grassmann import haar_frames

    A = haar_frames(1500, 3, 2, rng)
    b = rng.uniform(-1, 1, (1500, 3))
    val = np.sin(3 * b[:, :1]) + A[:, :1, 0]
    qA, qb = haar_frames(300, 3, 2, rng), rng.uniform(-1, 1, (300, 3))
    lib = AtlasField(Atlas.covering(2, 3).with_unit(1.0), channels=1)
    lib.add(Flats.from_parametric(A, b), val)
    want = lib.query(Flats.from_parametric(qA, qb), interpolant="gradient")
    linear = lib.query(Flats.from_parametric(qA, qb))
    assert want.inside.mean() > 0.8
    assert np.abs(want.values - linear.values)[want.inside].max() > 1e-3
    import asyncio

    from flatserve.field import Field

    on_loop = []

    def watched(query):
        def run(self, *a, **kw):  # a gradient query is never answered on the event loop
            if kw.get("interpolant") == "gradient":
                try:
                    asyncio.get_running_loop()
                    on_loop.append(True)
                except RuntimeError:
                    on_loop.append(False)
            return query(self, *a, **kw)
        return run

    for cls in (Field, AtlasField):
        monkeypatch.setattr(cls, "query", watched(cls.query))
    tc, c = started(make_app())
    try:
        c.create_field("p", k=2, d=3, unit=1.0)
        c.upload_parametric("p", A, b, val)
        for rows in (slice(None), slice(0, 10)):
            for binary in (True, False):
                got = c.query_parametric("p", qA[rows], qb[rows], binary=binary,
                                         interpolant="gradient")
                np.testing.assert_array_equal(got.inside, want.inside[rows])
                np.testing.assert_allclose(got.values, want.values[rows], rtol=0, atol=1e-12,
                                           equal_nan=True)
        assert on_loop and not any(on_loop), on_loop
        with pytest.raises(ServiceError) as err:
            c.query_parametric("p", qA, qb, interpolant="cubic")
        assert err.value.status == 422 and "interpolant" in str(err.value.detail)
        # one chart: rays, the library's one-chart field built as the service builds it
        o, v = sphere_rays(rng, 3000, spread=0.5)
        o, v = o[v[:, 2] > 0.5], v[v[:, 2] > 0.5]
        c.create_field("one", channels=C, basis=ONE_CHART)
        ref = SINGLE.reference(C)
        add_rays(ref, o, v, line_values(o, v))
        c.upload_rays("one", o, v, line_values(o, v))
        qo, qv = o[:200] + rng.normal(0, 0.02, (200, 3)), v[:200]
        want = ref.query(Flats.from_rays(qo, qv), interpolant="gradient")
        assert want.inside.mean() > 0.5
        got = c.query_rays("one", qo, qv, interpolant="gradient")
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-12, equal_nan=True)
    finally:
        tc.__exit__(None, None, None)
