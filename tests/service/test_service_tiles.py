"""A one-chart field in tiles over HTTP (``tiles`` at create): the answers of the
library's unsplit field, bit for bit, before and after a restart from its
snapshot; tiles refused for an atlas field."""
from __future__ import annotations

import numpy as np
from tests.harness.cells import assert_same_cells
from tests.harness.fields import SINGLE, add_rays, paper_rays
from tests.harness.service import running


def test_a_tiled_one_chart_field_answers_as_the_unsplit_one(make_app, rng):
    ref = SINGLE.reference(channels=2)
    o, v = paper_rays(rng, 6000)
    vals = rng.uniform(size=(6000, 2))
    qo, qv = paper_rays(rng, 3000)
    with running(make_app()) as (tc, c):
        info = c.create_field("t", basis=SINGLE.basis, channels=2, tiles=4)
        assert info["tiles"] == 4 and info["ncharts"] == 1
        for i in range(0, 6000, 1500):  # batches across the tiles' borders
            c.upload_rays("t", o[i:i + 1500], v[i:i + 1500], vals[i:i + 1500])
            add_rays(ref, o[i:i + 1500], v[i:i + 1500], vals[i:i + 1500])
        want = ref.query_rays(qo, qv, return_weights=True)
        got = c.query_rays("t", qo, qv, weights=True)
        assert np.array_equal(got.values, want.values, equal_nan=True)
        assert_same_cells(want.ids, want.weights, got.ids, got.weights, want.inside)
        first = c.snapshot("t")
        assert first["written"] > 0
        assert c.describe("t")["nvertices"] == ref.nsamples
        # one part per tile: nothing changed, nothing written again
        e = tc.app.state.rooms.catalogue.get("t")
        assert len(tc.app.state.rooms.storage.snapshot_parts(e.id)) == 4
        c.upload_rays("t", o[:10], v[:10], vals[:10])  # the same rays again: no new sample
        add_rays(ref, o[:10], v[:10], vals[:10])
        again = c.snapshot("t")
        assert 0 < again["written"] < first["written"]
    with running(make_app()) as (tc, c):  # restored from its tiles' snapshot parts
        c.wait_ready(60)
        assert c.describe("t")["tiles"] == 4
        again = c.query_rays("t", qo, qv)
        assert np.array_equal(again.values, want.values, equal_nan=True)


def test_tiles_are_refused_for_an_atlas_field(make_app):
    with running(make_app()) as (tc, c):
        r = tc.post("/v1/fields", json={"name": "a", "tiles": 2})
        assert r.status_code == 422 and "tiles" in r.text
        r = tc.post("/v1/fields", json={"name": "a", "basis": SINGLE.basis, "tiles": 0})
        assert r.status_code == 422 and "tiles" in r.text
        r = tc.post("/v1/fields", json={"name": "a", "basis": SINGLE.basis, "tiles": "many"})
        assert r.status_code == 422 and "tiles" in r.text
        r = tc.post("/v1/fields", json={"name": "a", "tiles": "auto"})
        assert r.status_code == 422 and "tiles" in r.text  # an atlas field


def test_auto_tiles_over_http(make_app, rng, monkeypatch):
    """``"tiles": "auto"``: the field is cut into tiles as it grows (the threshold
    lowered here), described, and restored with its setting."""
    import flatserve.tiles as tiles_mod
    from flatserve.parallel import ShardPool

    monkeypatch.setattr(tiles_mod, "AUTO_MIN_SAMPLES", 2000)
    monkeypatch.setattr(tiles_mod, "shard_pool", lambda p=ShardPool(2): p)
    ref = SINGLE.reference(channels=1)
    o, v = paper_rays(rng, 3000)
    vals = rng.uniform(size=(3000, 1))
    qo, qv = paper_rays(rng, 1000)
    with running(make_app()) as (tc, c):
        info = c.create_field("t", basis=SINGLE.basis, channels=1, tiles="auto")
        assert info["tiles"] == "auto"
        c.upload_rays("t", o[:1000], v[:1000], vals[:1000])
        assert c.describe("t")["ntiles"] == 1
        c.upload_rays("t", o[1000:], v[1000:], vals[1000:])
        add_rays(ref, o, v, vals)
        assert c.describe("t")["ntiles"] == 2
        want = ref.query_rays(qo, qv)
        assert np.array_equal(c.query_rays("t", qo, qv).values, want.values, equal_nan=True)
        c.snapshot("t")
    with running(make_app()) as (tc, c):
        c.wait_ready(60)
        d = c.describe("t")
        assert d["tiles"] == "auto" and d["ntiles"] == 2
        assert tc.app.state.rooms.catalogue.get("t").field.triangulation.auto  # from the file
        assert np.array_equal(c.query_rays("t", qo, qv).values, want.values, equal_nan=True)


def test_a_replayed_tiled_field_holds_the_same_bytes(make_app, rng):
    """The tiles depend on the log alone: a batch goes in whole with its exchange
    (whatever queries came in meanwhile, and whatever ``insert_slice_rows``), so a
    server that replays the log holds the very bytes of the one that took the
    uploads."""
    o, v = paper_rays(rng, 4500)
    vals = rng.uniform(size=(4500, 1))
    qo, qv = paper_rays(rng, 500)
    with running(make_app(insert_slice_rows=500)) as (tc, c):
        c.create_field("t", basis=SINGLE.basis, channels=1, tiles=3)
        for i in range(0, 4500, 1500):  # 3 slices' worth each, a query between batches
            c.upload_rays("t", o[i:i + 1500], v[i:i + 1500], vals[i:i + 1500])
            c.query_rays("t", qo, qv)
        tri = tc.app.state.rooms.catalogue.get("t").field.triangulation
        assert tri.settled and len(tri.stats.rounds) == 3  # one exchange per batch
        first = tc.app.state.rooms.catalogue.get("t").field.to_bytes()
    with running(make_app(insert_slice_rows=500)) as (tc, c):  # no snapshot: the log again
        c.wait_ready(60)
        assert tc.app.state.rooms.catalogue.get("t").field.to_bytes() == first
