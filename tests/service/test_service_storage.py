"""Durability in-process: restart from batches, from snapshots, from damaged snapshots;
concurrency invariants (a query never sees half a batch); for the default (atlas)
field and for one chart alike."""
from __future__ import annotations

import os
import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.client import Client
from flatserve.flats import Flats

from tests.harness.fields import KINDS, paper_rays
from tests.harness.service import save_bytes, started as _started
from tests.harness.storage import check_clean_up_under_field_leases

with_kinds = pytest.mark.parametrize("kind", KINDS, ids=str)


def _upload_some(c, rng, name="f", batches=3, n=400, channels=2, basis=None):
    c.create_field(name, channels=channels, basis=basis)
    sent = []
    for i in range(batches):
        o, v = paper_rays(rng, n)
        val = rng.normal(size=(n, channels))
        c.upload_rays(name, o, v, val, idempotency_key=f"b{i}")
        sent.append((o, v, val))
    return sent


def _answers(c, probe, kind, name="f"):
    """Values, inside and (one chart: an atlas field returns none) simplices."""
    res = c.query_rays(name, *probe, weights=not kind.atlas)
    return res.values, res.inside, res.ids


def _same(a, b):
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])
    np.testing.assert_allclose(a[0], b[0], atol=1e-12, equal_nan=True)


@with_kinds
@pytest.mark.parametrize("snapshot", ["none", "middle", "end"])
def test_restart_restores_same_field(make_app, rng, snapshot, kind):
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=2, basis=kind.basis)
        for i in range(4):
            o, v = paper_rays(rng, 300)
            c.upload_rays("f", o, v, rng.normal(size=(300, 2)), idempotency_key=f"b{i}")
            if (snapshot == "middle" and i == 1) or (snapshot == "end" and i == 3):
                snap = c.snapshot("f")
                assert snap["batch"] == i + 1 and snap["bytes"] > 0
        probe = paper_rays(rng, 300)
        before, info = _answers(c, probe, kind), c.describe("f")
        assert (info["nrejected"] == 0) == kind.atlas
    finally:
        tc.__exit__(None, None, None)
    tc, c = _started(make_app())
    try:
        after = c.describe("f")
        for key in ("nsamples", "nrejected", "nvertices", "nsimplex", "atlas", "charts"):
            assert after.get(key) == info.get(key), key
        expect = {"none": 0, "middle": 2, "end": 4}[snapshot]
        assert after["storage"]["snapshot_batch"] == expect
        _same(before, _answers(c, probe, kind))
        # a retried upload after the restart is recognised
        assert len(c.batches("f")) == 4
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_damaged_snapshot_rebuilds_from_batches(make_app, rng, tmp_path, caplog, kind):
    tc, c = _started(make_app())
    try:
        _upload_some(c, rng, basis=kind.basis)
        c.snapshot("f")
        probe = paper_rays(rng, 200)
        before = _answers(c, probe, kind)
    finally:
        tc.__exit__(None, None, None)
    snaps = list((tmp_path / "data" / "snapshots").glob("*.snap"))
    assert len(snaps) == 1
    data = snaps[0].read_bytes()
    snaps[0].write_bytes(data[: len(data) // 2])
    (tmp_path / "data" / "snapshots" / ".tmp-leftover").write_bytes(b"junk")
    with caplog.at_level("INFO", logger="flatserve"):
        tc, c = _started(make_app())
    try:
        assert "rebuilding from batches" in caplog.text
        _same(before, _answers(c, probe, kind))
        names = {p.name for p in (tmp_path / "data" / "snapshots").iterdir()}
        assert ".tmp-leftover" not in names
    finally:
        tc.__exit__(None, None, None)


def test_background_snapshot_after_enough_samples(make_app, rng, tmp_path):
    tc, c = _started(make_app(snapshot_every=500))
    try:
        c.create_field("f")
        for i in range(3):
            o, v = paper_rays(rng, 300)
            c.upload_rays("f", o, v, np.ones(300))
        for _ in range(200):
            if c.describe("f")["storage"]["snapshot_batch"] >= 2:
                break
            threading.Event().wait(0.05)
        st = c.describe("f")["storage"]
        assert st["snapshot_batch"] >= 2 and st["snapshot_bytes"] > 0
        assert st["total_bytes"] == st["batch_bytes"] + st["snapshot_bytes"]
    finally:
        tc.__exit__(None, None, None)


def test_delete_removes_batches_and_snapshot(make_app, rng, tmp_path):
    tc, c = _started(make_app())
    try:
        _upload_some(c, rng)
        c.snapshot("f")
        snaps = tmp_path / "data" / "snapshots"
        assert len(list((snaps / "parts").iterdir())) > 1  # an atlas field: its charts' parts
        c.delete_field("f")
        assert not [p for p in snaps.rglob("*") if not p.is_dir()]  # nor its parts
        _upload_some(c, rng, batches=1)  # same name again: a new, empty field
        assert len(c.batches("f")) == 1
    finally:
        tc.__exit__(None, None, None)
    tc, c = _started(make_app())
    try:
        assert [f["name"] for f in c.list_fields()] == ["f"]
        assert len(c.batches("f")) == 1
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_queries_never_see_half_a_batch(make_app, rng, kind):
    """Per batch, a concurrent query at its accepted rays matches their values exactly
    either for all of them (inserted) or for none (not yet inserted); an atlas field's
    batch is in every chart or in none."""
    tc, c = _started(make_app(workers=8))
    try:
        c.create_field("f", basis=kind.basis)
        o0, v0 = paper_rays(rng, 500)
        c.upload_rays("f", o0, v0, rng.uniform(size=(500, 1)))
        batches = []
        for _ in range(6):
            o, v = paper_rays(rng, 400)
            batches.append((o, v, rng.uniform(2, 3, size=(400, 1))))  # values outside [0, 1]
        stop = threading.Event()
        seen, errors = [], []

        def reader():
            cl = Client(http=tc)
            while not stop.is_set():
                try:
                    for j, (o, v, val) in enumerate(batches):
                        res = cl.query_rays("f", o, v)
                        hit = np.isclose(res.values[:, 0], val[:, 0], atol=1e-9)
                        seen.append((j, int(hit.sum())))
                except Exception as exc:  # pragma: no cover - reported below
                    errors.append(exc)
                    return

        threads = [threading.Thread(target=reader) for _ in range(3)]
        for t in threads:
            t.start()
        accepted = []
        for o, v, val in batches:
            accepted.append(c.upload_rays("f", o, v, val)["accepted"])
        stop.set()
        for t in threads:
            t.join()
        assert not errors, errors
        assert seen
        for j, hits in seen:
            assert hits in (0, accepted[j]), (j, hits, accepted[j])
    finally:
        tc.__exit__(None, None, None)


def test_uploads_to_one_field_are_serialised(make_app, rng):
    tc, c = _started(make_app(workers=8))
    try:
        c.create_field("f")
        payloads = [paper_rays(rng, 200) + (rng.uniform(size=(200, 1)),) for _ in range(8)]
        reports = [None] * 8

        def up(i):
            o, v, val = payloads[i]
            reports[i] = Client(http=tc).upload_rays("f", o, v, val, idempotency_key=f"k{i}")

        ts = [threading.Thread(target=up, args=(i,)) for i in range(8)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        seqs = sorted(r["batch"] for r in reports)
        assert seqs == list(range(1, 9))
        # the batch stored last reports the final size
        last = max(reports, key=lambda r: r["batch"])
        assert last["nsamples"] == c.describe("f")["nsamples"]
    finally:
        tc.__exit__(None, None, None)


@with_kinds
def test_restore_never_goes_past_its_log_position(make_app, rng, kind):
    """A snapshot replaced while a replica restores (another replica wrote a newer
    one) must not carry the field past the log position the restore read: the
    replica would answer at position p with batches committed after p."""
    _restore_to_its_position(make_app(), rng, kind)


def test_restore_never_goes_past_its_log_position_postgresql(make_app, rng, pg_url):
    _restore_to_its_position(make_app(database_url=pg_url), rng, KINDS[1])


def _restore_to_its_position(app, rng, kind):
    from flatserve.service.rooms import applier as applier_mod

    tc, c = _started(app)
    try:
        reg = app.state.rooms
        c.create_field("f", channels=2, basis=kind.basis)
        for i in range(2):
            o, v = paper_rays(rng, 300)
            c.upload_rays("f", o, v, rng.normal(size=(300, 2)), idempotency_key=f"b{i}")
        assert c.snapshot("f")["batch"] == 2
        probe = paper_rays(rng, 200)
        at_two = _answers(c, probe, kind)
        head, rows = reg.storage.state()  # what a starting replica reads
        (row,) = rows
        assert row.snapshot_seq == 2
        o, v = paper_rays(rng, 300)  # meanwhile: a third batch and a newer snapshot
        c.upload_rays("f", o, v, rng.normal(size=(300, 2)), idempotency_key="b2")
        assert c.snapshot("f")["batch"] == 3
        # the starting replica restores the row it read, to the head it read
        e = applier_mod.entry_of(row)
        reg.applier._restore(e, row, upto=head)
        assert e.state == "ready", e.error
        assert e.indexed_seq == 2 and e.indexed_position <= head
        res = e.field.query(Flats.from_rays(*probe), threads=1)
        np.testing.assert_array_equal(res.inside, at_two[1])
        np.testing.assert_allclose(res.values, at_two[0], atol=1e-12, equal_nan=True)
    finally:
        tc.__exit__(None, None, None)


def test_a_stray_directory_among_the_snapshots_does_not_stop_the_start(make_app, rng, tmp_path):
    """The start-up clean-up of unreferenced snapshot files meets something it cannot
    remove (a directory: ``lost+found`` of a volume mounted there): it is kept, and
    the server still restores its fields and becomes ready."""
    tc, c = _started(make_app())
    try:
        c.create_field("f", channels=1)
        c.upload_rays("f", *paper_rays(rng, 300), np.ones(300))
        c.snapshot("f")
    finally:
        tc.__exit__(None, None, None)
    (tmp_path / "data" / "snapshots" / "lost+found").mkdir()
    tc, c = _started(make_app())
    try:
        assert c.describe("f")["nsamples"] > 0
    finally:
        tc.__exit__(None, None, None)
    assert (tmp_path / "data" / "snapshots" / "lost+found").is_dir()


def test_a_stored_field_this_version_cannot_read_fails_alone(make_app, rng, tmp_path):
    """A stored definition that cannot be read (here: a spec with k = "one") fails
    that field only: the others restore and answer, /readyz is 200 and lists it in
    failed_fields, its own requests get 503 naming the error, and it can be deleted."""
    import sqlite3

    from flatserve.service.log.storage import DB_NAME

    tc, c = _started(make_app())
    try:
        c.create_field("f")
        c.create_field("g")
        o, v = paper_rays(rng, 200)
        c.upload_rays("f", o, v, np.ones(200))
        c.upload_rays("g", o, v, np.ones(200))
        want = c.query_rays("f", o[:20], v[:20])
    finally:
        tc.__exit__(None, None, None)
    db = sqlite3.connect(tmp_path / "data" / DB_NAME)
    with db:
        db.execute("""UPDATE fields SET spec='{"k": "one", "d": 3}' WHERE name='g'""")
    db.close()
    tc = TestClient(base_url="http://127.0.0.1", app=make_app())
    tc.__enter__()
    try:
        c = Client(http=tc)
        c.wait_ready(20)
        r = tc.get("/readyz").json()
        assert r["status"] == "ready" and r["failed_fields"] == ["g"] and r["failed"] == 1
        got = c.query_rays("f", o[:20], v[:20])
        np.testing.assert_array_equal(got.values, want.values)
        states = {f["name"]: f["state"] for f in c.list_fields()}
        assert states == {"f": "ready", "g": "failed"}
        for r in (tc.get("/v1/fields/g"),
                  tc.post("/v1/fields/g/query", json={"origins": o[:2].tolist(),
                                                      "directions": v[:2].tolist()})):
            assert r.status_code == 503 and "cannot be read" in r.text, r.text
        assert tc.delete("/v1/fields/g").status_code == 204
        assert "g" not in {f["name"] for f in c.list_fields()}
    finally:
        tc.__exit__(None, None, None)


def _open_at_once(data, fd, start, out):
    from flatserve.service.log.storage import SQLiteBackend

    start.wait()
    try:
        SQLiteBackend(data, lock_fd=fd).close()
        out.put("ok")
    except Exception as exc:  # reported by the test
        out.put(repr(exc))


def test_replicas_opening_a_new_data_dir_at_once_all_open(tmp_path):
    """The replicas of one group (processes) start together on an empty directory:
    each opens the database (WAL switch, schema) while the others do; none may fail
    with 'database is locked' (a replica of --processes N would exit)."""
    import multiprocessing as mp

    from flatserve.service.log.storage import lock_data_dir

    ctx = mp.get_context("fork")
    for rnd in range(20):
        data = tmp_path / f"d{rnd}"
        fd = lock_data_dir(data)
        start, out = ctx.Barrier(8), ctx.Queue()
        ps = [ctx.Process(target=_open_at_once, args=(data, fd, start, out)) for _ in range(8)]
        for p in ps:
            p.start()
        got = [out.get(timeout=120) for _ in ps]
        for p in ps:
            p.join(30)
        os.close(fd)
        assert got == ["ok"] * 8, (rnd, got)


def test_sqlite_lease_renewal_and_a_snapshot_removed_before_it_is_pointed_at(tmp_path):
    """renew_lease: True while the owner holds the lease without a break, False once
    it expired (even if free again: another replica may have cleaned up meanwhile).
    A snapshot file removed between its write and the pointing transaction (that
    clean-up) is refused: the field keeps no dangling snapshot."""
    import time

    from flatserve.service.status import StorageError
    from flatserve.service.log.storage import SQLiteBackend, lock_data_dir

    fd = lock_data_dir(tmp_path / "data")
    be = SQLiteBackend(tmp_path / "data", lock_fd=fd)
    try:
        fid, _ = be.create_field("f", {"k": 1}, {"Q": np.eye(3)[None].repeat(5, 0),
                                                 "r": np.zeros((5, 3))})
        assert be.acquire_lease("snapshot", "A", 300) and be.renew_lease("snapshot", "A", 300)
        assert not be.renew_lease("snapshot", "B", 300)
        assert be.acquire_lease("snapshot", "A", 0.05)
        time.sleep(0.1)  # expired: taken by B, cleaned up under it, released
        assert be.acquire_lease("snapshot", "B", 300)
        be.release_lease("snapshot", "B")
        assert not be.renew_lease("snapshot", "A", 300)  # lapsed, though free now

        def removed_meanwhile():  # the clean-up of a replica holding the lease
            for p in be.snapshot_dir.glob(".tmp-*"):
                os.replace(p, be.snapshot_dir / "moved-away")
            be.clean_orphans()

        with pytest.raises(StorageError):  # (no file to publish)
            be.write_snapshot(fid, 0, 0, save_bytes(b"snap"), removed_meanwhile)
        assert be.field(fid).snapshot_file is None
    finally:
        be.close()
        os.close(fd)


def test_sqlite_clean_up_takes_each_fields_lease(tmp_path):
    from flatserve.service.log.storage import SQLiteBackend, lock_data_dir

    fd = lock_data_dir(tmp_path / "data")
    be = SQLiteBackend(tmp_path / "data", lock_fd=fd)
    try:
        check_clean_up_under_field_leases(be)
    finally:
        be.close()
        os.close(fd)
