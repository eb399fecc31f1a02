"""The cost guard (``max_simplices``) judges from the field's last complete state,
never from a triangulation with a batch half inserted; a refusal that may pass
later is a 429 with ``Retry-After``, a 413 only one that cannot."""
from __future__ import annotations

import threading
import time

import numpy as np

from flatserve.service import applier as applier_mod

from .conftest import SINGLE, paper_rays, started


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
