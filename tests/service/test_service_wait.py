"""Uploads with ``?wait=false`` (acknowledged once stored and charted, indexed in the
background), the two-phase insert behind them, and readiness during a restore; for the
default (atlas) field and for one chart alike."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve import flats
from flatserve.client import Client
from flatserve.field import Field
from flatserve.service.rooms import applier as applier_mod
from flatserve.service import assembly
from flatserve.service.rooms import specs
from flatserve.service.status import NotReadyError
from tests.harness.fields import DEFAULT, KINDS, add_rays, paper_rays, query_rays
from tests.harness.service import started as _started

C = 2
with_kinds = pytest.mark.parametrize("kind", KINDS, ids=str)


def _ref():
    return Field(specs.build_basis(None, 1, 3), channels=C)


def _rays_with_rejects(rng, n):
    """Paper rays, a tenth of them turned parallel to the screen (outside the single
    chart; an atlas accepts them)."""
    o, v = paper_rays(rng, n)
    bad = rng.choice(n, n // 10, replace=False)
    v[bad, 2] = 0.0
    return o, v, rng.normal(size=(n, C))


def _upload(c, ref, rng, n=300, **kw):
    """Upload ``n`` fresh rays (a tenth rejected) to field "f" and add them to the
    reference field ``ref`` too; the upload's report."""
    o, v, val = _rays_with_rejects(rng, n)
    add_rays(ref, o, v, val)
    return c.upload_rays("f", o, v, val, **kw)


def _same_answers(got, want):
    """Same inside mask, values and (inside the hull; one chart) simplices. Outside it,
    the hull facet reported depends on where the walk starts, which a snapshot load
    changes."""
    np.testing.assert_array_equal(got.inside, want.inside)
    if want.ids is not None:
        np.testing.assert_array_equal(got.ids[got.inside], want.ids[want.inside])
    np.testing.assert_allclose(got.values, want.values, atol=1e-12, equal_nan=True)


def _got(c, kind, probe):
    """The service's answers at ``probe`` (with simplices for one chart)."""
    return c.query_rays("f", *probe, weights=not kind.atlas)


def _want(ref, kind, probe):
    return query_rays(ref, *probe, return_weights=not kind.atlas)


@pytest.mark.parametrize("form", ["rays", "parametric", "flats"])
def test_prepare_then_insert_equals_field_add(rng, form):
    """The service's two-phase insert leaves the field exactly as Field.add* does
    (bit for bit: the restore replays batches through Field.add*)."""
    a, b = _ref(), _ref()
    for _ in range(3):
        o, v, val = _rays_with_rejects(rng, 300)
        if form == "rays":
            batch, want = flats.Flats.from_rays(o, v), a.add_rays(o, v, val)
        elif form == "parametric":
            A = (v / np.linalg.norm(v, axis=1, keepdims=True))[:, :, None]
            batch = flats.Flats.from_parametric(A, o)
            want = a.add(batch, val)
        else:
            Q, r = flats.from_rays(o, v)
            batch = flats.Flats.from_quadrics(Q, r, 1)
            want = a.add(batch, val)
        p = b.prepare(batch, val)
        assert p.accepted == want.accepted and p.accepted < 300
        np.testing.assert_array_equal(p.rejected, want.rejected)
        assert p.reasons == want.reasons
        res = b.insert_prepared(p)
        dup, n = res.duplicates, res.nsamples
        assert (dup, n) == (want.duplicates, want.nsamples)
    assert (b.nsamples, b.nrejected, b.nsimplex) == (a.nsamples, a.nrejected, a.nsimplex)
    np.testing.assert_array_equal(b.triangulation.points, a.triangulation.points)
    qo, qv = paper_rays(rng, 300)
    _same_answers(b.query_rays(qo, qv, return_weights=True),
                  a.query_rays(qo, qv, return_weights=True))


class _Gate:
    """Holds the log follower (before it locks the field) at batches after ``after``
    until ``open()``."""

    def __init__(self, monkeypatch, after=0):
        self.event = threading.Event()
        self.entered = threading.Event()

        def gated(e, seq):
            if seq <= after:
                return
            self.entered.set()
            self.event.wait(30)

        monkeypatch.setattr(applier_mod.LogApplier, "_before_index", staticmethod(gated))

    def open(self):
        self.event.set()


@with_kinds
def test_wait_false_acknowledges_then_indexes_in_commit_order(make_app, rng, monkeypatch, kind):
    gate = _Gate(monkeypatch, after=1)  # batch 1 (wait=true) is applied before its answer
    ref = kind.reference(C)
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C, basis=kind.basis)
        base = _upload(c, ref, rng, 400)  # wait=true: indexed in the request
        assert base["indexed"] and base["nsamples"] == ref.nsamples
        probe = paper_rays(rng, 300)
        before = _want(ref, kind, probe)

        sent, reps = [], []
        for i in range(3):
            o, v, val = _rays_with_rejects(rng, 300)
            rep = c.upload_rays("f", o, v, val, wait=False, idempotency_key=f"k{i}",
                                binary=bool(i % 2))
            # accepted/rejected depend on the basis (or atlas) only
            want = add_rays(kind.reference(C), o, v, val)
            assert (want.accepted == len(o)) == kind.atlas
            assert not rep["indexed"] and rep["duplicates"] is None
            assert rep["accepted"] == want.accepted
            assert rep["rejected"] == want.rejected.tolist()
            assert rep["reasons"] == want.reasons
            sent.append((o, v, val))
            reps.append(rep)
        assert [r["batch"] for r in reps] == [2, 3, 4]
        gate.entered.wait(30)
        info = c.describe("f")
        assert info["indexed_batch"] == 1 and info["storage"]["last_batch"] == 4
        assert info["pending_batches"] == 3
        assert info["pending_samples"] == sum(r["accepted"] for r in reps)
        assert info["nsamples"] == ref.nsamples
        # queries see the indexed batches only; a snapshot covers only them
        _same_answers(_got(c, kind, probe), before)
        assert c.snapshot("f")["batch"] == 1
        # a retry is recognised while pending
        again = c.upload_rays("f", *sent[0], wait=False, idempotency_key="k0")
        assert again["replayed"] and again["batch"] == 2
        gate.open()
        info = c.wait_indexed("f", timeout=30)
        for o, v, val in sent:
            add_rays(ref, o, v, val)
        assert info["indexed_batch"] == 4 and info["pending_samples"] == 0
        assert (info["nsamples"], info["nrejected"]) == (ref.nsamples, ref.nrejected)
        want = _want(ref, kind, probe)
        _same_answers(_got(c, kind, probe), want)
        assert c.upload_rays("f", *sent[0], idempotency_key="k0")["indexed"]
    finally:
        tc.__exit__(None, None, None)
    # restart: from the snapshot after batch 1 plus the replayed batches 2-4
    tc, c = _started(make_app())
    try:
        info = c.describe("f")
        assert info["storage"]["snapshot_batch"] == 1 and info["indexed_batch"] == 4
        assert info["nsamples"] == ref.nsamples
        _same_answers(_got(c, kind, probe), want)
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_wait_true_after_wait_false_sees_every_earlier_batch(make_app, rng, kind):
    ref = kind.reference(C)
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C, basis=kind.basis)
        for i in range(4):
            rep = _upload(c, ref, rng, wait=i == 3)
        assert rep["indexed"] and rep["batch"] == 4 and rep["nsamples"] == ref.nsamples
        info = c.describe("f")
        assert info["pending_batches"] == 0 and info["indexed_batch"] == 4
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_shutdown_leaves_pending_batches_to_the_replay(make_app, rng, monkeypatch, kind):
    """A batch acknowledged with wait=false but not indexed at shutdown is replayed."""
    monkeypatch.setattr(assembly, "DRAIN_TIMEOUT_S", 0.2)
    gate = _Gate(monkeypatch)
    ref = kind.reference(C)
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C, basis=kind.basis)
        for _ in range(2):
            assert not _upload(c, ref, rng, wait=False)["indexed"]
        gate.entered.wait(30)
        assert c.describe("f")["indexed_batch"] == 0
    finally:
        tc.__exit__(None, None, None)  # drains for 0.2 s only: the gate is still shut
        gate.open()
    monkeypatch.undo()
    tc, c = _started(make_app())
    try:
        info = c.describe("f")
        assert info["indexed_batch"] == 2 and info["nsamples"] == ref.nsamples
        probe = paper_rays(rng, 200)
        _same_answers(_got(c, kind, probe), _want(ref, kind, probe))
    finally:
        tc.__exit__(None, None, None)


def test_readyz_is_503_while_stored_fields_restore(make_app, rng, monkeypatch):
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C)
        o, v, val = _rays_with_rejects(rng, 200)
        c.upload_rays("f", o, v, val)
    finally:
        tc.__exit__(None, None, None)
    release, entered = threading.Event(), threading.Event()
    real = applier_mod.LogApplier._restore

    def slow_restore(self, e, row):
        entered.set()
        release.wait(30)
        return real(self, e, row)

    monkeypatch.setattr(applier_mod.LogApplier, "_restore", slow_restore)
    with TestClient(base_url="http://127.0.0.1", app=make_app()) as tc:
        try:
            assert entered.wait(30)
            r = tc.get("/readyz")
            assert r.status_code == 503 and r.json()["status"] == "loading"
            assert tc.get("/healthz").status_code == 200
            r = tc.post("/v1/fields/f/query", json={"origins": o[:2].tolist(),
                                                    "directions": v[:2].tolist()})
            assert r.status_code == 503 and r.headers.get("Retry-After")
        finally:
            release.set()
        Client(http=tc).wait_ready(30)
        assert tc.get("/readyz").status_code == 200
        assert tc.get("/v1/fields/f").json()["nsamples"] > 0


def test_wait_false_refuses_bad_rays_and_stores_nothing(make_app, rng):
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C)
        o, v, val = _rays_with_rejects(rng, 50)
        v[7] = 0.0  # a zero direction: refused when the coordinates are computed
        r = tc.post("/v1/fields/f/samples", params={"wait": "false"},
                    json={"origins": o.tolist(), "directions": v.tolist(),
                          "values": val.tolist()})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "directions"]
        info = c.describe("f")
        assert info["storage"]["batches"] == 0 and info["pending_batches"] == 0
        v[7] = 1.0
        assert c.upload_rays("f", o, v, val, wait=False)["batch"] == 1
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_wait_false_response_lost_in_a_crash_is_recomputed(make_app, rng, tmp_path, kind):
    """A wait=false batch is committed while its coordinates are computed, and its
    response is stored after, without an fsync: if a crash loses that row, a retry
    with the same key gets the same answer, recomputed from the stored arrays."""
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C, basis=kind.basis)
        o, v, val = _rays_with_rejects(rng, 300)
        first = c.upload_rays("f", o, v, val, wait=False, idempotency_key="k")
        assert not first["replayed"]
        # one chart rejects the rays beyond it (with reasons); the atlas none
        assert (first["rejected"] == [] and first["accepted"] == 300) == kind.atlas
        assert len(first["reasons"]) == len(first["rejected"])
        c.wait_indexed("f", timeout=30)
    finally:
        tc.__exit__(None, None, None)
    import sqlite3

    db = sqlite3.connect(tmp_path / "data" / "flatserve.sqlite3")
    with db:
        assert db.execute("SELECT COUNT(*) FROM batch_results").fetchone()[0] == 1
        db.execute("DELETE FROM batch_results")
    db.close()
    tc, c = _started(make_app())
    try:
        listed = tc.get("/v1/fields/f/batches").json()["batches"]
        assert [(b["batch"], b["accepted"]) for b in listed] == [(1, None)]  # not recomputed
        again = c.upload_rays("f", o, v, val, wait=False, idempotency_key="k")
        assert again["replayed"] and again["indexed"]
        for key in ("batch", "accepted", "rejected", "reasons"):
            assert again[key] == first[key]
        listed = tc.get("/v1/fields/f/batches").json()["batches"]
        assert [(b["batch"], b["accepted"]) for b in listed] == [(1, first["accepted"])]
        assert c.describe("f")["nsamples"] == first["accepted"]
    finally:
        tc.__exit__(None, None, None)


def test_wait_false_failure_after_the_commit_leaves_nothing_stored(make_app, rng, monkeypatch):
    """The batch is committed while its coordinates are computed; if computing them
    fails (unexpectedly), the client gets an error and the batch is removed again:
    nothing half-stored, the field stays usable and a later retry stores it once."""
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C)
        o, v, val = _rays_with_rejects(rng, 200)
        real = Field.chart

        def boom(self, *a, **kw):
            raise MemoryError("simulated")

        monkeypatch.setattr(Field, "chart", boom)
        tc_raise = TestClient(base_url="http://127.0.0.1", app=tc.app, raise_server_exceptions=False)
        r = tc_raise.post("/v1/fields/f/samples", params={"wait": "false"},
                          headers={"Idempotency-Key": "k1"},
                          json={"origins": o.tolist(), "directions": v.tolist(),
                                "values": val.tolist()})
        assert r.status_code >= 500
        info = c.describe("f")
        assert info["state"] == "ready" and info["storage"]["batches"] == 0
        monkeypatch.setattr(Field, "chart", real)
        rep = c.upload_rays("f", o, v, val, wait=False, idempotency_key="k1")
        assert rep["batch"] == 1 and not rep["replayed"]
        c.wait_indexed("f", timeout=30)
        assert c.describe("f")["nsamples"] == rep["accepted"]
    finally:
        tc.__exit__(None, None, None)


def test_a_committed_upload_waits_a_bounded_time_then_503_stored(make_app, rng, monkeypatch):
    """A wait=true upload whose batch is committed but not applied within
    apply_wait_timeout (the follower held, as in a database outage): 503 with
    Retry-After saying the batch is stored; the retry with the same key gets its
    response once applied, and the batch is stored once."""
    gate = _Gate(monkeypatch)
    tc, c = _started(make_app(apply_wait_timeout=0.3))
    try:
        c.create_field("f", channels=C)
        o, v, val = _rays_with_rejects(rng, 200)
        with pytest.raises(NotReadyError, match="is stored"):
            c.upload_rays("f", o, v, val, idempotency_key="k")
        r = c.last_response
        assert r.status_code == 503 and r.headers["retry-after"] == "1"
        with pytest.raises(NotReadyError, match="is stored"):  # a retry meanwhile: the same
            c.upload_rays("f", o, v, val, idempotency_key="k")
        r = tc.post("/v1/fields/f/query", params={"wait": "true"},
                    json={"origins": o[:2].tolist(), "directions": v[:2].tolist()})
        assert r.status_code == 503 and r.headers["retry-after"] == "1", r.text
        gate.open()
        again = c.upload_rays("f", o, v, val, idempotency_key="k")
        ref = DEFAULT.reference(C)
        want = add_rays(ref, o, v, val)
        assert again["replayed"] and again["indexed"] and again["batch"] == 1
        assert again["accepted"] == want.accepted
        d = c.describe("f")
        assert d["storage"]["last_batch"] == 1 and d["nsamples"] == ref.nsamples
    finally:
        gate.open()
        tc.__exit__(None, None, None)


def test_a_field_failed_between_commit_and_insert_is_503_not_404(make_app, rng, monkeypatch):
    """The field is marked failed (not deleted) after a wait=true batch is committed
    and before the follower reaches it: 503 saying the batch is stored, not 404."""
    gate = _Gate(monkeypatch)  # holds the follower at batch 1
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C)
        o, v, val = _rays_with_rejects(rng, 200)
        c.upload_rays("f", o[:100], v[:100], val[:100], wait=False)
        assert gate.entered.wait(30)
        reg = tc.app.state.rooms
        e = reg.catalogue.get("f")
        out = {}

        def upload():
            try:
                # retries=0: this answer itself (the client retries a 503 by default)
                out["ok"] = Client(http=tc, retries=0).upload_rays(
                    "f", o[100:], v[100:], val[100:], idempotency_key="k2")
            except Exception as exc:
                out["exc"] = exc

        th = threading.Thread(target=upload, daemon=True)
        th.start()
        while reg.storage.head() < 3 and th.is_alive():  # create, batch 1, batch 2
            threading.Event().wait(0.01)
        reg.applier.fail_field(e.id, "marked failed by the test")
        gate.open()
        th.join(60)
        assert isinstance(out.get("exc"), NotReadyError), out
        assert "batch 2 is stored" in str(out["exc"])
        assert reg.catalogue.by_id(e.id) is e and not e.deleted
    finally:
        gate.open()
        tc.__exit__(None, None, None)


class _ShardCounts:
    """Stands in for a cluster field's ``applied_counts`` (the counts its shard groups
    give once they have applied a batch) on an in-process field: the field's samples
    now and no duplicates (the test's rays are distinct); records the time each call
    is given."""

    def __init__(self, field):
        self.field, self.timeouts = field, []

    def __call__(self, position: int, timeout: float) -> dict:
        self.timeouts.append(timeout)
        return {"nsamples": self.field.nsamples, "duplicates": 0}


def _counted_by_shards(tc, monkeypatch) -> _ShardCounts:
    field = tc.app.state.rooms.catalogue.get("f").field
    counts = _ShardCounts(field)
    monkeypatch.setattr(field, "applied_counts", counts, raising=False)
    return counts


def test_a_retried_wait_true_upload_keeps_its_response_and_fills_in_a_wait_false_one(
        make_app, rng, monkeypatch):
    """A retry with wait=true of a batch answered whole (wait=true) gets that answer
    again, its counts as they were, though the shards count more samples by now; a
    retry of one acknowledged before its insert (wait=false) gets the shards' counts."""
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=C)
        counts = _counted_by_shards(tc, monkeypatch)
        whole, early = _rays_with_rejects(rng, 200), _rays_with_rejects(rng, 200)
        first = c.upload_rays("f", *whole, idempotency_key="whole")
        acked = c.upload_rays("f", *early, idempotency_key="early", wait=False)
        assert not acked["indexed"] and acked["duplicates"] is None
        c.wait_indexed("f")
        c.upload_rays("f", *_rays_with_rejects(rng, 200))  # the field grows past both
        assert c.describe("f")["nsamples"] > first["nsamples"]
        again = c.upload_rays("f", *whole, idempotency_key="whole")
        assert again["replayed"]
        assert (again["nsamples"], again["duplicates"]) == (first["nsamples"],
                                                           first["duplicates"])
        filled = c.upload_rays("f", *early, idempotency_key="early")
        assert filled["replayed"] and filled["indexed"]
        assert {k: filled[k] for k in ("nsamples", "duplicates")} == counts(0, 0.0)
    finally:
        tc.__exit__(None, None, None)


def test_a_wait_true_upload_waits_for_the_shards_within_what_is_left_of_its_timeout(
        make_app, rng, monkeypatch):
    """The shards are given what is left of ``apply_wait_timeout`` after the wait
    for the insert here, on an upload and on its retry: the 503 comes within the one
    timeout, not two."""
    timeout, here = 2.0, 0.4
    tc, c = _started(make_app(apply_wait_timeout=timeout))
    try:
        c.create_field("f", channels=C)
        counts = _counted_by_shards(tc, monkeypatch)
        follower = tc.app.state.rooms.follower
        real = follower.await_applied

        def slow(*args, **kw):
            threading.Event().wait(here)
            return real(*args, **kw)

        monkeypatch.setattr(follower, "await_applied", slow)
        batch = _rays_with_rejects(rng, 200)
        c.upload_rays("f", *batch, idempotency_key="k")
        c.upload_rays("f", *batch, idempotency_key="k")
        assert len(counts.timeouts) == 2
        assert all(0 <= t <= timeout - here for t in counts.timeouts), counts.timeouts
    finally:
        tc.__exit__(None, None, None)
