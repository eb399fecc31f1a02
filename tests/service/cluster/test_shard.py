"""Shard workers (``flatserve/service/cluster/worker/shard.py``) in this process, on a REAL
PostgreSQL log, behind a front's :class:`RemoteField` with the groups called
directly (no Ray: tests/service/cluster/test_cluster.py runs them as actors).

A snapshot of a field held by shard workers: the workers store their own charts'
parts in the database and the front's snapshot writer receives none of their
bytes (its staging directory stays empty); workers started afresh restore from
those parts and answer as the lone server that applied the same log, bit for bit.
"""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from flatserve.basis import Basis
from flatserve.contract import POINTER_MAGIC, load_field
from flatserve.flats import Flats
from flatserve.service.log.backend import open_backend
from flatserve.service.cluster import wire
from flatserve.service.cluster.front.remote import RemoteField
from flatserve.service.cluster.worker.shard import ShardWorker
from flatserve.service.rooms.entry import FieldSpec
from flatserve.service.settings import Settings

from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.service import started


class LocalGroups:
    """:class:`~flatserve.service.cluster.front.remote.ShardGroups` over workers of this
    process, one copy per group."""

    def __init__(self, workers):
        self.workers = workers
        self.charts = [w.charts for w in workers]

    def call(self, calls, timeout):
        return {g: call.run(self.workers[g]) for g, call in calls.items()}

    def status(self):
        return [w.status() for w in self.workers]

    def placement(self):
        return []

    def refresh(self):
        pass

    def applied(self, position, timeout):
        got = self.call({g: wire.applied(position, timeout) for g in range(len(self.workers))},
                        timeout)
        return [got[g] for g in range(len(self.workers))]


def _sphere(rng, n):
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 3))


def _workers(settings, row, head, groups, timeout=120.0):
    """Workers of ``groups`` of field ``row``, once each has applied the log up to
    position ``head``."""
    ws = [ShardWorker(settings, row.id, charts) for charts in groups]
    end = time.monotonic() + timeout
    while not all(s["state"] == "ready" and s["through"] >= head
                  for s in (w.status() for w in ws)):
        assert time.monotonic() < end, [w.status() for w in ws]
        time.sleep(0.1)
    return ws


def _remote(storage, row, head, workers):
    spec = FieldSpec.from_dict(row.spec)
    shape = spec.new_field(Basis(row.basis["Q"], row.basis["r"], spec.k))
    return RemoteField(shape, LocalGroups(workers), lambda: head, timeout=60)


def _snapshot(storage, row, remote):
    """A snapshot of the field written as a front writes it; the bytes that passed
    through the front's staging directory, and the snapshot's info."""
    known = storage.snapshot_parts(row.id)
    staged = []

    def save(path, stage):
        keys = remote.save_parts(path, stage, known)
        staged.extend(os.listdir(stage))
        return keys

    last = list(storage.batches(row.id))[-1]
    info = storage.write_snapshot(row.id, last.seq, last.position, save)
    return staged, info


@pytest.mark.parametrize("kind", ["atlas", "one"])
def test_shards_store_their_own_parts_and_restore_from_them(make_app, pg_url, rng, kind):
    settings = Settings(database_url=pg_url)
    tc, c = started(make_app(database_url=pg_url))
    storage = open_backend(settings)
    workers = []
    try:
        if kind == "atlas":
            c.create_field("f", channels=2)
            make = _sphere
        else:
            c.create_field("f", channels=2, basis=ONE_CHART)
            make = paper_rays
        for _ in range(2):
            o, d = make(rng, 2000)
            c.upload_rays("f", o, d, rng.uniform(size=(2000, 2)), wait=True)
        row = next(r for r in storage.state()[1] if r.name == "f")
        head = storage.head()
        ncharts = len(FieldSpec.from_dict(row.spec).new_field(
            Basis(row.basis["Q"], row.basis["r"], 1)).shards)
        groups = [tuple(range(g, ncharts, 2)) for g in range(min(2, ncharts))]
        workers = _workers(settings, row, head, groups)
        remote = _remote(storage, row, head, workers)

        staged, info = _snapshot(storage, row, remote)
        assert staged == []  # no part's bytes through the front
        assert remote.stored_bytes > 0
        assert storage.snapshot_bytes(info.file) >= remote.stored_bytes
        # nothing changed since: every part is known, nothing is serialised or stored
        staged, _ = _snapshot(storage, row, remote)
        assert staged == [] and remote.stored_bytes == 0
        for w in workers:
            w.stop()

        row = storage.field(row.id)
        pointer = storage.load_snapshot(row, lambda path, parts: open(path, "rb").read(8))
        assert (pointer == POINTER_MAGIC) == (kind == "one")
        # the snapshot as a lone server reads it: the field the app holds, bit for bit
        whole = storage.load_snapshot(row, lambda path, parts: load_field(path, parts))
        probe = make(rng, 500)
        mine = c.query_rays("f", *probe)
        got = whole.query(Flats.from_rays(*probe))
        np.testing.assert_array_equal(got.values, mine.values)
        np.testing.assert_array_equal(got.inside, mine.inside)

        # workers started afresh restore their charts from the parts, and answer the same
        workers = _workers(settings, row, head, groups)
        assert all(w.restored_from == f"snapshot after batch {row.snapshot_seq}"
                   for w in workers)
        remote = _remote(storage, row, head, workers)
        got = remote.query(Flats.from_rays(*probe))
        np.testing.assert_array_equal(got.values, mine.values)
        np.testing.assert_array_equal(got.inside, mine.inside)
    finally:
        for w in workers:
            w.stop()
        storage.close()
        tc.__exit__(None, None, None)


def test_two_snapshots_of_a_worker_store_their_parts_one_after_the_other(
        make_app, pg_url, rng, monkeypatch):
    """Two fronts snapshot the same field at once: a worker serialises one call's
    parts after the other (each holds the worker at its own position and counts its
    own bytes; overlapping, the first's end released the second's hold)."""
    import threading

    from flatserve.atlas_field import AtlasField

    settings = Settings(database_url=pg_url)
    tc, c = started(make_app(database_url=pg_url))
    storage = open_backend(settings)
    workers = []
    try:
        c.create_field("f", channels=1)
        o, d = _sphere(rng, 1500)
        c.upload_rays("f", o, d, rng.uniform(size=(1500, 1)), wait=True)
        row = next(r for r in storage.state()[1] if r.name == "f")
        head = storage.head()
        workers = _workers(settings, row, head, [(0, 1, 2, 3)])
        (w,) = workers
        real, seen = AtlasField.chart_parts, []

        def slow(self, charts, known):
            seen.append(("in", threading.get_ident()))
            time.sleep(0.2)
            seen.append(("out", threading.get_ident()))
            return real(self, charts, known)

        monkeypatch.setattr(AtlasField, "chart_parts", slow)
        got = []
        calls = [threading.Thread(target=lambda: got.append(w.parts(head, (), 30.0)))
                 for _ in range(2)]
        for t in calls:
            t.start()
        for t in calls:
            t.join()
        assert len(got) == 2 and got[0]["seq"] == got[1]["seq"] == 1
        assert len(seen) == 16  # 2 calls x 4 charts, in and out
        firsts = [tid for _, tid in seen[:8]]
        assert len(set(firsts)) == 1, seen  # one call's 4 charts, then the other's
        assert got[0]["stored"] > 0 and got[1]["stored"] == 0  # (a part is stored once)
    finally:
        for w in workers:
            w.stop()
        storage.close()
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_store_part_stores_once(tmp_path, request, backend):
    url = request.getfixturevalue("pg_url") if backend == "postgresql" else None
    settings = Settings(data_dir=tmp_path / "data", database_url=url)
    st = open_backend(settings)
    try:
        fid, _ = st.create_field("f", {"k": 1, "d": 3, "channels": 1, "basis": {}},
                                 {"Q": np.eye(3)[None].repeat(2, 0), "r": np.zeros((2, 3))})
        assert st.store_part(fid, "ab" * 16, b"x" * 1000) == 1000
        assert st.store_part(fid, "ab" * 16, b"x" * 1000) == 0  # there already
        assert st.snapshot_parts(fid) == {"ab" * 16}
    finally:
        st.close()


class _OneWorker:
    """:class:`~flatserve.service.cluster.front.remote.ShardGroups` of one group holding every
    chart of ``field`` (a library field), as a shard worker reports at batch ``seq``;
    the parts it stores land in ``store``."""

    def __init__(self, field, seq: int, store: dict):
        self.field, self.seq, self.store = field, seq, store
        self.charts = [tuple(range(len(field.shards)))]

    def call(self, calls, timeout):
        parts = []
        for c, key, blob in self.field.chart_parts(self.charts[0]):
            self.store[key] = blob
            parts.append((c, key))
        return {0: {"seq": self.seq, "parts": parts, "whole": None, "tiles": [],
                    "unit": self.field.atlas.unit, "own": self.field.own_samples,
                    "nrejected": self.field.nrejected, "stored": 0}}

    def status(self):
        return [None]  # (no report yet)


def test_a_shard_restored_after_the_first_batch_keeps_its_unit_and_samples(rng):
    """Two batches uploaded before the first was applied both record a unit (each
    chosen from its own rows); the first in the log sets it. A snapshot in parts
    after batch 1, written by the front's empty definition (which inserts nothing
    and so would still take a unit), must leave the unit fixed: a shard restored from
    it and given batch 2's unit keeps its samples and its unit (it rebuilt its
    charts, emptied, in the second unit before the header said so)."""
    import io

    from flatserve.atlas import Atlas
    from flatserve.atlas_field import AtlasField
    from flatserve.service.rooms.units import adopt_unit

    def batch(n):
        o, v = rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 3))
        return Flats.from_rays(o, v), np.sin(3 * o[:, :1]) + v[:, :1]

    atlas = Atlas.covering(1, 3, unit="fit").to_dict()
    (f1, v1), (f2, v2) = batch(600), batch(600)
    u1, u2 = 0.5, 0.9  # recorded with batch 1 and batch 2
    worker = AtlasField(Atlas.from_dict(atlas), channels=1)
    adopt_unit(worker, u1)
    worker.insert_prepared(worker.prepare(f1, v1))
    store: dict = {}
    front = RemoteField(AtlasField(Atlas.from_dict(atlas), channels=1),
                        _OneWorker(worker, 1, store), lambda: 1, timeout=10.0)
    adopt_unit(front, u1)  # the front's applier, batch 1
    assert not front.unit_pending and front.atlas.unit == u1
    buf = io.BytesIO()
    front.write_parts(buf, "/nonexistent")
    restored = AtlasField.from_bytes(buf.getvalue(), parts=store.__getitem__)
    assert restored.atlas.unit == u1 and not restored.unit_from_data
    for fld in (restored, worker):  # batch 2, its unit recorded (ShardWorker._apply)
        adopt_unit(fld, u2)
        fld.insert_prepared(fld.prepare(f2, v2))
    assert restored.atlas.unit == worker.atlas.unit == u1
    assert (restored.nsamples, restored.nstored) == (worker.nsamples, worker.nstored)
    probe = batch(300)[0]
    np.testing.assert_array_equal(restored.query(probe).values, worker.query(probe).values)
    # a field that holds samples takes no other unit, whatever a snapshot said
    assert worker.settle_unit(2.0, if_empty=True) is False and worker.atlas.unit == u1
    # before the first batch the header leaves the unit open (the log's first batch sets it)
    empty = AtlasField(Atlas.from_dict(atlas), channels=1)
    buf = io.BytesIO()
    RemoteField(AtlasField(Atlas.from_dict(atlas), channels=1), _OneWorker(empty, 0, store),
                lambda: 0, timeout=10.0).write_parts(buf, "/nonexistent")
    assert AtlasField.from_bytes(buf.getvalue(), parts=store.__getitem__).unit_from_data


def test_a_remote_fields_decisions_are_charted_when_read(rng):
    """A remote field's prepared batch charts its decisions on first read (the
    applier reads them for a batch it charts again for an upload that waits):
    the rows its definition rejects are reported, as a local field reports them."""
    from flatserve.atlas import Atlas
    from flatserve.atlas_field import AtlasField
    from flatserve.service.rooms.applier import decided

    n = 300
    v = rng.normal(size=(n, 3)) * [0.2, 0.2, 1.0]
    v[::3] = rng.normal(size=(n // 3 if n % 3 == 0 else n // 3 + 1, 3)) * [1.0, 1.0, 0.05]
    o = rng.uniform(-1, 1, (n, 3))
    near_z = Flats.from_rays(o[v[:, 2] ** 2 > v[:, 0] ** 2 + v[:, 1] ** 2],
                             v[v[:, 2] ** 2 > v[:, 0] ** 2 + v[:, 1] ** 2])
    atlas = Atlas.for_samples(near_z, unit=1.0)
    flats, vals = Flats.from_rays(o, v), rng.uniform(size=(n, 1))
    want = AtlasField(atlas, channels=1).prepare(flats, vals)
    assert 0 < want.rejected.size < n  # (the rows far from z: no chart holds them)
    front = RemoteField(AtlasField(atlas, channels=1), _OneWorker(AtlasField(atlas, 1), 1, {}),
                        lambda: 1, timeout=10.0)
    lazy = front.prepare(flats, vals)
    assert front.insert_prepared(lazy).accepted == n  # undecided: every row reported
    lazy = front.prepare(flats, vals)
    decided(lazy)
    got = front.insert_prepared(lazy)
    assert got.accepted == want.accepted
    np.testing.assert_array_equal(got.rejected, want.rejected)


@pytest.mark.parametrize("seam", ["net", "dense"])
def test_shard_workers_thin_a_seam_as_the_server_does(make_app, pg_url, rng, seam):
    """Planes in R^4 with a thinner seam (the default's net of the outer seam, or a
    seam narrowed after 25 own samples) in two batches: workers following the log
    store each of their charts' samples as the server does, a worker restored from
    the snapshot between the batches as well, and the front's copies of a batch (the
    upload guard's) are the server's (with ``dense_after``: judged by the charts' own
    samples the workers report)."""
    from flatserve.grassmann import haar_frames

    settings = Settings(database_url=pg_url)
    tc, c = started(make_app(database_url=pg_url))
    storage = open_backend(settings)
    workers = []
    try:
        c.create_field("p", k=2, d=4, channels=1, unit=1.0, **({} if seam == "net" else {
            "basis": {"kind": "atlas", "atlas": "covering", "inner": 2, "trusted": 6,
                      "reach": 14, "dense_reach": 9, "dense_after": 25}}))
        A, b = haar_frames(1600, 4, 2, rng), rng.uniform(-1, 1, (1600, 4))
        val = np.sin(2 * b[:, :1])
        c.upload_parametric("p", A[:900], b[:900], val[:900], wait=True)
        row = next(r for r in storage.state()[1] if r.name == "p")
        groups = [tuple(range(g, 59, 2)) for g in range(2)]
        workers = _workers(settings, row, storage.head(), groups)
        remote = _remote(storage, row, storage.head(), workers)
        _snapshot(storage, row, remote)
        for w in workers:
            w.stop()
        c.upload_parametric("p", A[900:], b[900:], val[900:], wait=True)
        row, head = storage.field(row.id), storage.head()
        workers = _workers(settings, row, head, groups)
        assert all(w.restored_from.startswith("snapshot") for w in workers)
        remote = _remote(storage, row, head, workers)
        info = c.describe("p", verbose=True)
        per_chart = [ch["samples"] for ch in info["charts"]]
        got = [0] * 59
        for w in workers:
            st = w.status()
            for ch, n in zip(st["charts"], st["chart_samples"]):
                got[ch] = n
        assert got == per_chart and sum(per_chart) == info["atlas"]["nstored"]
        # the one-process field of the same batches, and the front's copies of a new
        # batch: judged by the charts' own samples (the workers' reports), not all sparse
        lib = FieldSpec.from_dict(row.spec).new_field(Basis(row.basis["Q"], row.basis["r"], 2))
        fresh = FieldSpec.from_dict(row.spec).new_field(Basis(row.basis["Q"], row.basis["r"], 2))
        for rows in (slice(0, 900), slice(900, 1600)):
            lib.add(Flats.from_parametric(A[rows], b[rows]), val[rows])
        assert [f.nsamples for f in lib.shards] == per_chart
        probe = Flats.from_parametric(haar_frames(2000, 4, 2, rng), np.zeros((2000, 4)))
        assert remote.copies(probe) == lib.copies(probe)
        if seam == "dense":
            assert lib.copies(probe) < fresh.copies(probe)
    finally:
        for w in workers:
            w.stop()
        storage.close()
        tc.__exit__(None, None, None)
