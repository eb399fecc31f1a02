"""Snapshots in parts through the service, on both backends: a snapshot after a
batch that touched one chart writes that chart's part only; restarts restore
from the parts, from an old whole-field snapshot, or (a part damaged) from the
batches, answering as before."""
from __future__ import annotations

import numpy as np
import pytest

from tests.harness.charts import rays_in_one_chart

from tests.harness.fields import paper_rays
from tests.harness.service import started

BACKENDS = ["sqlite", "postgresql"]


def _opts(request, backend):
    return {} if backend == "sqlite" else {"database_url": request.getfixturevalue("pg_url")}


def _answers(c, probe):
    res = c.query_rays("f", *probe)
    return res.values, res.inside


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_batch_in_one_chart_writes_one_part(make_app, rng, request, backend):
    opts = _opts(request, backend)
    tc, c = started(make_app(**opts))
    try:
        c.create_field("f")  # the default: a covering atlas, one part per chart
        o, v = paper_rays(rng, 3000)
        c.upload_rays("f", o, v, rng.uniform(size=3000))
        first = c.snapshot("f")
        assert first["written"] == first["bytes"] > 0  # nothing stored before: every part
        e = tc.app.state.rooms.catalogue.get("f")
        ncharts = len(e.field.shards)
        o1, v1 = rays_in_one_chart(e.field, rng, 3, 200)
        c.upload_rays("f", o1, v1, rng.uniform(size=200))
        second = c.snapshot("f")
        chart_bytes = len(e.field.shards[3].to_bytes())
        # the changed chart's part and the small field file; not the other charts
        assert second["written"] < chart_bytes + first["bytes"] / ncharts, (second, chart_bytes)
        assert second["bytes"] > first["bytes"]
        again = c.snapshot("f")  # nothing changed since: the stored one
        assert again["written"] == 0 and again["batch"] == second["batch"]
        probe = paper_rays(rng, 300)
        before = _answers(c, probe)
    finally:
        tc.__exit__(None, None, None)
    tc, c = started(make_app(**opts))  # restored from the parts
    try:
        info = c.describe("f")
        assert info["storage"]["snapshot_batch"] == 2
        after = _answers(c, probe)
        np.testing.assert_array_equal(after[0], before[0])
        np.testing.assert_array_equal(after[1], before[1])
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_old_whole_field_snapshot_still_loads(make_app, rng, request, backend, caplog):
    opts = _opts(request, backend)
    tc, c = started(make_app(**opts))
    try:
        c.create_field("f")
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, rng.uniform(size=2000))
        rooms = tc.app.state.rooms
        e = rooms.catalogue.get("f")
        # as written before snapshots had parts: the whole field in one file
        rooms.storage.write_snapshot(e.id, e.indexed_seq, e.indexed_position,
                                     lambda path, _stage: e.field.save(path))
        assert rooms.storage.snapshot_parts(e.id) == set()
        probe = paper_rays(rng, 300)
        before = _answers(c, probe)
    finally:
        tc.__exit__(None, None, None)
    with caplog.at_level("INFO", logger="flatserve"):
        tc, c = started(make_app(**opts))
    try:
        assert "snapshot after batch 1 loaded" in caplog.text
        after = _answers(c, probe)
        np.testing.assert_array_equal(after[0], before[0])
        # its next snapshot is in parts
        o, v = paper_rays(rng, 100)
        c.upload_rays("f", o, v, rng.uniform(size=100))
        snap = c.snapshot("f")
        e = tc.app.state.rooms.catalogue.get("f")
        assert snap["written"] == snap["bytes"]
        assert len(tc.app.state.rooms.storage.snapshot_parts(e.id)) == len(e.field.shards)
    finally:
        tc.__exit__(None, None, None)


def test_a_damaged_part_rebuilds_from_the_batches(make_app, rng, tmp_path, caplog):
    tc, c = started(make_app())
    try:
        c.create_field("f")
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, rng.uniform(size=2000))
        c.snapshot("f")
        probe = paper_rays(rng, 300)
        before = _answers(c, probe)
    finally:
        tc.__exit__(None, None, None)
    parts = sorted((tmp_path / "data" / "snapshots" / "parts").iterdir(),
                   key=lambda p: p.stat().st_size)
    victim = parts[-1]
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    with caplog.at_level("INFO", logger="flatserve"):
        tc, c = started(make_app())
    try:
        assert "is damaged" in caplog.text and "rebuilding from batches" in caplog.text
        after = _answers(c, probe)
        np.testing.assert_array_equal(after[0], before[0])
        np.testing.assert_array_equal(after[1], before[1])
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_parts_of_an_abandoned_snapshot_are_removed(make_app, rng, request, backend):
    """Parts stored ahead of a snapshot that is then abandoned (as a cluster's shard
    groups store theirs before one of them turns out ahead of the others) do not
    stay: the field keeps the parts it had; the next snapshot writes its own."""
    from flatserve.client import ServiceError
    from flatserve.service.status import NotReadyError

    tc, c = started(make_app(**_opts(request, backend)))
    try:
        c.create_field("f")
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, rng.uniform(size=2000))
        first = c.snapshot("f")
        rooms = tc.app.state.rooms
        e = rooms.catalogue.get("f")
        had = rooms.storage.snapshot_parts(e.id)
        o, v = paper_rays(rng, 500)
        c.upload_rays("f", o, v, rng.uniform(size=500))
        real = e.field.save_parts

        def ahead(path, stage, known=()):
            rooms.storage.store_part(e.id, "ab" * 16, b"a part of the abandoned snapshot")
            raise NotReadyError("a shard group is ahead of the others; retry the snapshot")

        e.field.save_parts = ahead
        with pytest.raises(ServiceError) as err:
            c.snapshot("f")
        assert err.value.status == 503
        assert rooms.storage.snapshot_parts(e.id) == had
        e.field.save_parts = real
        second = c.snapshot("f")
        assert second["batch"] == first["batch"] + 1
        assert "ab" * 16 not in rooms.storage.snapshot_parts(e.id)
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_parts_are_read_when_asked_and_a_replaced_snapshot_is_gone(make_app, rng, request,
                                                                   backend):
    """``read_part`` gives a stored part's bytes (its key checks them) and names a
    missing one; a load that finds a part gone while the field's snapshot was
    replaced meanwhile is told to read the new one (``SnapshotGoneError``), while
    the same failure on the field's current snapshot is the load's own error."""
    from flatserve.contract import load_field, part_key
    from flatserve.errors import SnapshotError
    from flatserve.service.log.rows import SnapshotGoneError

    tc, c = started(make_app(**_opts(request, backend)))
    try:
        c.create_field("f")
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, rng.uniform(size=2000))
        c.snapshot("f")
        storage = tc.app.state.rooms.storage
        e = tc.app.state.rooms.catalogue.get("f")
        old = storage.field(e.id)
        keys = storage.snapshot_parts(e.id)
        assert keys and all(part_key(storage.read_part(e.id, k)) == k for k in keys)
        with pytest.raises(SnapshotError, match="missing"):
            storage.read_part(e.id, "cd" * 16)
        assert storage.load_snapshot(old, load_field).nsamples == 2000
        # a batch in the same charts, a new snapshot: their old parts are removed
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, rng.uniform(size=2000))
        c.snapshot("f")
        gone = sorted(keys - storage.snapshot_parts(e.id))
        assert gone

        def late(path, parts):  # the old snapshot's file read, a part gone since
            return parts(gone[0])

        with pytest.raises(SnapshotGoneError):
            storage.load_snapshot(old, late)
        new = storage.field(e.id)
        with pytest.raises(SnapshotError, match="missing"):
            storage.load_snapshot(new, late)
    finally:
        tc.__exit__(None, None, None)


def _paused_in_check(storage, pause):
    """``storage.write_snapshot`` with ``pause(field_id)`` run where the writer
    checks its lease, just before the field would point at its stored data."""
    write = storage.write_snapshot

    def paused(field_id, seq, position, save, check=None):
        def checked():
            pause(field_id)
            if check is not None:
                check()
        return write(field_id, seq, position, save, checked)

    return write, paused


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_fields_snapshot_at_once_in_one_replica(make_app, rng, request, backend):
    """Each field's writer holds its own lease: two fields' snapshots written at
    once in one process both succeed, whichever finishes first (the first done
    must not release the other's lease), round after round; each snapshot keeps
    all of its parts (one field's clean-up never takes the other's)."""
    import threading

    from flatserve.contract import load_field

    tc, c = started(make_app(**_opts(request, backend)))
    try:
        rooms = tc.app.state.rooms
        names = ("a", "b")
        for name in names:
            c.create_field(name)
        ids = {rooms.catalogue.get(n).id: n for n in names}
        rows = dict.fromkeys(names, 0)
        both_in, first_done = threading.Barrier(2, timeout=30), threading.Event()

        def pause(field_id):  # both writers hold their lease here; "b" waits for "a"
            both_in.wait()
            if ids[field_id] == "b":
                assert first_done.wait(30)

        write, paused = _paused_in_check(rooms.storage, pause)
        rooms.storage.write_snapshot = paused
        for rnd in range(4):
            for name in names:
                n = int(rng.integers(300, 800))
                c.upload_rays(name, *paper_rays(rng, n), rng.uniform(size=n))
                rows[name] += n
            both_in.reset()
            first_done.clear()
            got = {}

            def snap(name):
                got[name] = tc.post(f"/v1/fields/{name}/snapshot")
                if name == "a":
                    first_done.set()

            threads = [threading.Thread(target=snap, args=(n,)) for n in names]
            for t in threads:
                t.start()
            for t in threads:
                t.join(60)
            for name in names:
                r = got[name]
                assert r.status_code == 200, (rnd, name, r.text)
                assert r.json()["batch"] == rnd + 1
        rooms.storage.write_snapshot = write
        for name in names:
            e = rooms.catalogue.get(name)
            row = rooms.storage.field(e.id)
            assert row.snapshot_seq == 4
            assert rooms.storage.load_snapshot(row, load_field).nsamples == rows[name]
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_clean_up_leaves_another_fields_snapshot_being_written(make_app, rng, request,
                                                                  backend):
    """A replica starting (its clean-up of what a dead writer left) while another
    field's snapshot is on its way: the data not yet pointed at is that writer's,
    under the field's lease, and stays; the snapshot is written. A dead writer's
    data of a field nobody writes is removed."""
    import threading

    from flatserve.contract import load_field
    from flatserve.service.rooms.snapshots import SnapshotWriter
    from flatserve.service.status import StorageError

    tc, c = started(make_app(**_opts(request, backend)))
    try:
        rooms = tc.app.state.rooms
        c.create_field("f")
        c.upload_rays("f", *paper_rays(rng, 2000), rng.uniform(size=2000))
        fid = rooms.catalogue.get("f").id
        inside, go = threading.Event(), threading.Event()

        def pause(_field_id):
            inside.set()
            assert go.wait(30)

        write, paused = _paused_in_check(rooms.storage, pause)
        rooms.storage.write_snapshot = paused
        got = {}
        t = threading.Thread(target=lambda: got.setdefault("r", tc.post("/v1/fields/f/snapshot")))
        t.start()
        try:
            assert inside.wait(30)
            SnapshotWriter(rooms.settings, rooms.storage).clean_orphans()  # another replica's
        finally:
            go.set()
            t.join(60)
        rooms.storage.write_snapshot = write
        assert got["r"].status_code == 200, got["r"].text
        row = rooms.storage.field(fid)
        assert rooms.storage.load_snapshot(row, load_field).nsamples == 2000
        # data stored by no lease holder (a writer that died): the clean-up removes
        # it, and pointing the field at it is refused
        with pytest.raises(StorageError):
            rooms.storage.write_snapshot(
                fid, row.snapshot_seq + 1, row.snapshot_position,
                lambda path, _stage: path.write_bytes(b"a dead writer's") and None,
                check=SnapshotWriter(rooms.settings, rooms.storage).clean_orphans)
        assert rooms.storage.field(fid).snapshot_file == row.snapshot_file
        assert rooms.storage.load_snapshot(row, load_field).nsamples == 2000
        assert rooms.storage.clean_orphans() == 0
    finally:
        tc.__exit__(None, None, None)


def test_a_second_snapshot_of_a_field_in_the_same_replica_waits_its_turn(make_app, rng):
    """The replica's writers share its lease owner, so a second writer of the same
    field is refused before the lease (503 with Retry-After) instead of renewing
    the first's lease and releasing it under it; the first is written."""
    import threading

    tc, c = started(make_app())
    try:
        rooms = tc.app.state.rooms
        c.create_field("f")
        c.upload_rays("f", *paper_rays(rng, 1000), rng.uniform(size=1000))
        inside, go, calls = threading.Event(), threading.Event(), []

        def pause(_field_id):  # the first writer waits here, holding the field's lease
            calls.append(_field_id)
            if len(calls) == 1:
                inside.set()
                assert go.wait(30)

        write, paused = _paused_in_check(rooms.storage, pause)
        rooms.storage.write_snapshot = paused
        got = {}
        t = threading.Thread(target=lambda: got.setdefault("r", tc.post("/v1/fields/f/snapshot")))
        t.start()
        try:
            assert inside.wait(30)
            second = tc.post("/v1/fields/f/snapshot")
        finally:
            go.set()
            t.join(60)
        rooms.storage.write_snapshot = write
        assert second.status_code == 503 and "being written" in second.text, second.text
        assert second.headers["retry-after"]
        assert got["r"].status_code == 200, got["r"].text
        assert c.describe("f")["storage"]["snapshot_batch"] == 1
    finally:
        tc.__exit__(None, None, None)
