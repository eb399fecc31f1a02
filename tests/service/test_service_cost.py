"""The cost guard (``max_simplices``) judges from the field's last complete state,
never from a triangulation with a batch half inserted; a refusal that may pass
later is a 429 with ``Retry-After``, a 413 only one that cannot."""
from __future__ import annotations

import threading
import time

import numpy as np

from flatserve.service.rooms import applier as applier_mod
from tests.harness.fields import SINGLE, paper_rays
from tests.harness.service import started


def _rays_body(o, v, values):
    return {"origins": o.tolist(), "directions": v.tolist(), "values": values.tolist()}


def test_a_batch_half_inserted_does_not_inflate_the_estimate(make_app, rng):
    """While a large wait=false batch goes in slice by slice, the triangulation's cell
    count runs ahead of its vertex count (the cells per sample of a half-built
    4-D triangulation read 37-151 instead of about 30): uploads that fit by the
    complete state's measure are all accepted meanwhile."""
    tc, c = started(make_app(max_simplices=3_500_000, insert_slice_rows=10_000))
    try:
        c.create_field("f", channels=1, basis=SINGLE.basis)
        o, v = paper_rays(rng, 5000)
        c.upload_rays("f", o, v, rng.uniform(size=5000))
        info = c.describe("f")
        per = info["nsimplex"] / info["nsamples"]
        big = 100_000
        assert (5000 + big + 50) * per < 3_500_000 < (5000 + big) * per * 1.25  # fits, tightly
        o, v = paper_rays(rng, big)
        c.upload_rays("f", o, v, rng.uniform(size=big), wait=False)
        statuses, t_end = [], time.monotonic() + 120
        while c.describe("f")["pending_samples"] and time.monotonic() < t_end:
            o1, v1 = paper_rays(rng, 1)
            r = tc.post("/v1/fields/f/samples", params={"wait": "false"},
                        json=_rays_body(o1, v1, np.ones((1, 1))))
            statuses.append(r.status_code)
            assert r.status_code == 200, r.text
        assert len(statuses) >= 3  # the insert was under way for several of them
    finally:
        tc.__exit__(None, None, None)


def test_refusal_counting_pending_samples_is_429_and_413_only_when_it_cannot_pass(
        make_app, rng, monkeypatch):
    gate = threading.Event()
    held = set()

    def gated(e, seq):
        if seq in held:
            gate.wait(60)

    monkeypatch.setattr(applier_mod.LogApplier, "_before_index", staticmethod(gated))
    tc, c = started(make_app(max_simplices=1_000_000))
    try:
        c.create_field("f", channels=1, basis=SINGLE.basis)
        o, v = paper_rays(rng, 80_000)
        c.upload_rays("f", o[:5000], v[:5000], rng.uniform(size=5000))
        info = c.describe("f")
        per = info["nsimplex"] / info["nsamples"]
        capacity = 1_000_000 / per  # samples the limit allows at this measure
        pend = int(capacity * 0.5)
        n = int(capacity * 0.45)
        assert 5000 + pend < capacity < 5000 + pend + n and 5000 + n < capacity
        held.add(2)
        c.upload_rays("f", o[5000:5000 + pend], v[5000:5000 + pend], np.ones(pend), wait=False)
        lo = 5000 + pend
        r = tc.post("/v1/fields/f/samples", params={"wait": "false"},
                    json=_rays_body(o[lo:lo + n], v[lo:lo + n], np.ones((n, 1))))
        assert r.status_code == 429, r.text
        assert r.headers["retry-after"] == "1"
        assert "not yet indexed" in r.text and "FLATSERVE_MAX_SIMPLICES" in r.text
        # a batch that would not fit even without the pending samples: 413, at once
        m = int(capacity) - 5000 + 100
        r = tc.post("/v1/fields/f/samples", params={"wait": "false"},
                    json=_rays_body(o[lo:lo + m], v[lo:lo + m], np.ones((m, 1))))
        assert r.status_code == 413, r.text
        assert c.describe("f")["storage"]["batches"] == 2  # nothing refused was stored
        gate.set()
        c.wait_indexed("f", timeout=60)
        # indexed now, the same batch cannot pass any more: 413, not another 429
        r = tc.post("/v1/fields/f/samples",
                    json=_rays_body(o[lo:lo + n], v[lo:lo + n], np.ones((n, 1))))
        assert r.status_code == 413, r.text
    finally:
        gate.set()
        tc.__exit__(None, None, None)


def test_a_kind_that_could_not_hold_min_field_samples_is_refused_at_create(make_app):
    """``POST /v1/fields``: the samples a field could hold, max_simplices / (cells per
    sample of its dimension D x the charts holding each sample), below
    ``min_field_samples`` is a 413 naming the kind, D, the estimate, max_simplices and
    both settings; nothing is stored. The copies count: at 40,000 cells the default atlas
    of lines in R^3 (about 1.76 charts a sample: ~810 samples) is refused where one chart
    (~1,430) and points in R^2 (20,000) pass."""
    tc, c = started(make_app(max_simplices=40_000))
    try:
        r = tc.post("/v1/fields", json={"name": "lines", "channels": 1})
        assert r.status_code == 413, r.text
        msg = r.json()["detail"]
        assert "field 'lines' of lines in R^3 (k=1, d=3)" in msg, msg
        assert "dimension D = 4" in msg and "28 cells per sample" in msg, msg
        assert "charts holding each sample" in msg and "about 8" in msg, msg
        assert "max_simplices is 40,000" in msg and "min_field_samples = 1,000" in msg, msg
        assert "FLATSERVE_MAX_SIMPLICES" in msg and "FLATSERVE_MIN_FIELD_SAMPLES" in msg, msg
        assert c.list_fields() == [] and tc.get("/v1/fields/lines").status_code == 404
        assert c.create_field("one", channels=1, basis=SINGLE.basis)["nsamples"] == 0
        assert c.create_field("pts", k=0, d=2, channels=1)["nsamples"] == 0
        r = tc.post("/v1/fields", json={"name": "planes", "k": 2, "d": 4})
        assert r.status_code == 413 and "planes in R^4 (k=2, d=4)" in r.text, r.text
        assert "dimension D = 6" in r.text, r.text
        assert sorted(f["name"] for f in c.list_fields()) == ["one", "pts"]
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app(max_simplices=40_000, min_field_samples=500))
    try:  # the estimate passes the setting: created
        assert c.create_field("lines", channels=1)["ncharts"] == 16
    finally:
        tc.__exit__(None, None, None)


def test_default_settings_create_fields_up_to_planes_in_r4(api):
    """At the defaults (50M cells, 1,000 samples) lines and planes in R^4 (about 24k and
    13k samples) are created."""
    tc, c = api
    for name, k, d in (("l3", 1, 3), ("l4", 1, 4), ("p4", 2, 4), ("pts8", 0, 8)):
        r = tc.post("/v1/fields", json={"name": name, "k": k, "d": d})
        assert r.status_code == 201, r.text
