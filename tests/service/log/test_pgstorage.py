"""The PostgreSQL backend of the replica log (flatserve/service/log/pgstorage.py)
against a real PostgreSQL (a throwaway cluster, tests/conftest.py): the log's
order under concurrent writers of two backends, idempotency across them,
LISTEN/NOTIFY, snapshots as chunked rows, leases, and a restart of PostgreSQL
under a running backend."""
from __future__ import annotations

import threading
import time

import numpy as np
import psycopg
import pytest

from flatserve.service import status as fe
from flatserve.service.log.backend import open_backend, snapshot_lease
from flatserve.service.log.rows import KeyTakenError, SnapshotGoneError
from flatserve.service.log.blobs import pack_arrays, unpack_arrays
from flatserve.service.log.pgsnapshots import CHUNK_BYTES
from flatserve.service.log.pgstorage import PostgresBackend, redact
from flatserve.service.settings import Settings
from tests.harness.service import save_bytes
from tests.harness.storage import check_clean_up_under_field_leases

BASIS = {"Q": np.eye(3)[None].repeat(5, 0), "r": np.zeros((5, 3))}


@pytest.fixture
def two(pg_url):
    """Two backends on one database, as two replicas would hold."""
    a, b = PostgresBackend(pg_url), PostgresBackend(pg_url)
    a.check()
    b.check()
    yield a, b
    a.close()
    b.close()


def blob_of(rng, n=4):
    return pack_arrays({"origins": rng.normal(size=(n, 3)), "values": rng.uniform(size=(n, 1))})


def test_backend_is_chosen_by_the_url_scheme(pg_url, tmp_path):
    be = open_backend(Settings(database_url=pg_url, data_dir=tmp_path))
    try:
        assert isinstance(be, PostgresBackend) and be.kind == "postgresql"
        be.check()
        assert be.head() == 0
    finally:
        be.close()
    assert redact("postgresql://u:secret@db.example:5433/x?sslmode=require") == \
        "postgresql://u:***@db.example:5433/x?sslmode=require"
    assert "secret" not in PostgresBackend("postgresql://u:secret@h/x").where


def test_concurrent_appends_are_seen_in_commit_order_by_an_incremental_reader(two):
    """Writers on two backends append to three fields at once; a follower reading
    ``read_log(after=last seen)`` in a loop must end up with every entry: an entry
    that committed below a position already passed would be lost to it."""
    a, b = two
    rng = np.random.default_rng(7)
    fids = [a.create_field(f"f{i}", {"i": i}, BASIS)[0] for i in range(3)]
    blobs = [blob_of(rng, 256) for _ in range(8)]
    stop = threading.Event()
    seen: list[int] = []
    acked: list[tuple[int, int, int]] = []  # (field, seq, position)
    lock = threading.Lock()

    def follow():
        last = 0
        while True:
            done = stop.is_set()
            for e in b.read_log(last, limit=64):
                seen.append(e.position)
                last = e.position
            if done:
                return

    def write(be, w):
        r = np.random.default_rng(w)
        for i in range(60):
            fid = fids[int(r.integers(3))]
            seq, pos = be.add_batch(fid, idem_key=f"w{w}-{i}", chash="h", form="rays",
                                    nrows=256, blob=blobs[i % 8])
            with lock:
                acked.append((fid, seq, pos))

    follower = threading.Thread(target=follow)
    follower.start()
    writers = [threading.Thread(target=write, args=(be, w)) for w, be in enumerate([a, b, a, b])]
    for t in writers:
        t.start()
    for t in writers:
        t.join()
    stop.set()
    follower.join()

    full = [e.position for e in a.read_log(0, limit=10_000)]
    assert seen == full  # nothing skipped, nothing twice, in order
    assert len(acked) == 240 and {p for _, _, p in acked} <= set(full)
    for fid in fids:  # per field: seq 1, 2, ... and increasing with the position
        rows = a.batches(fid)
        assert [r.seq for r in rows] == list(range(1, len(rows) + 1))
        assert all(x.position < y.position for x, y in zip(rows, rows[1:]))
        assert sorted((s, p) for f, s, p in acked if f == fid) == [(r.seq, r.position) for r in rows]
    head, fields = b.state()
    assert head == full[-1] and [f.id for f in fields] == fids


def test_one_idempotency_key_is_stored_once_across_backends(two):
    a, b = two
    rng = np.random.default_rng(3)
    fid, _ = a.create_field("idem", {}, BASIS)
    blob = blob_of(rng)
    outcomes = []
    barrier = threading.Barrier(6)

    def put(be):
        barrier.wait()
        try:
            outcomes.append(be.add_batch(fid, idem_key="same", chash="h", form="rays", nrows=4,
                                         blob=blob, result_fn=lambda s, p: {"batch": s, "at": p}))
        except KeyTakenError as exc:
            outcomes.append(exc.existing)

    ts = [threading.Thread(target=put, args=(be,)) for be in [a, b] * 3]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    stored = [o for o in outcomes if isinstance(o, tuple)]
    assert len(stored) == 1
    seq, pos = stored[0]
    for o in outcomes:
        if not isinstance(o, tuple):
            assert (o.seq, o.position, o.result) == (seq, pos, {"batch": seq, "at": pos})
    assert a.find_batch(fid, "same").seq == seq and len(b.batches(fid)) == 1
    got = b.batch_arrays(fid, seq)
    want = unpack_arrays(blob)
    assert got.keys() == want.keys() and all(np.array_equal(got[k], want[k]) for k in got)
    # responses: replace, keep, and a deleted batch is a no-op
    b.set_result(fid, seq, {"v": 2})
    a.set_result(fid, seq, {"v": 3}, replace=False)
    assert a.find_batch(fid, "same").result == {"v": 2}
    a.delete_field(fid)
    b.set_result(fid, seq, {"v": 4})
    with pytest.raises(fe.FieldNotFoundError):
        b.add_batch(fid, idem_key=None, chash="h", form="rays", nrows=4, blob=blob)
    with pytest.raises(fe.FieldNotFoundError):
        b.batch_arrays(fid, seq)
    with pytest.raises(fe.FieldExistsError):
        a.create_field("x", {}, BASIS)
        b.create_field("x", {}, BASIS)


def test_follower_wakes_on_another_backends_commit_and_on_its_own(two):
    a, b = two
    rng = np.random.default_rng(5)
    fid, _ = a.create_field("wake", {}, BASIS)
    b.wait_for_change(0.01)  # the first call connects (and returns: LISTEN starts now)
    b.wait_for_change(0.01)
    head = b.head()
    timer = threading.Timer(0.3, lambda: a.add_batch(fid, idem_key=None, chash="h", form="rays",
                                                      nrows=4, blob=blob_of(rng)))
    timer.start()
    t0 = time.monotonic()
    while b.head() == head:  # woken by the NOTIFY, not the 60 s timeout
        b.wait_for_change(60)
        assert time.monotonic() - t0 < 30
    timer.join()
    # its own commit and wake() return at once (no NOTIFY round trip needed)
    b.add_batch(fid, idem_key=None, chash="h", form="rays", nrows=4, blob=blob_of(rng))
    t0 = time.monotonic()
    b.wait_for_change(60)
    b.wake()
    b.wait_for_change(60)
    threading.Timer(0.2, b.close).start()
    b.wait_for_change(60)  # close() ends a wait in progress
    assert time.monotonic() - t0 < 30


def test_snapshots_are_chunked_rows_replaced_whole_and_removed_with_their_field(two, pg_url):
    a, b = two
    rng = np.random.default_rng(11)
    fid, _ = a.create_field("snap", {}, BASIS)
    payloads = [rng.bytes(int(CHUNK_BYTES * 2.5)), rng.bytes(1000), b""]

    def saver(data, ext=""):
        def save(path, _stage):
            with open(str(path) + ext, "wb") as fh:
                fh.write(data)
        return save

    infos = []
    for i, data in enumerate(payloads):
        seq, pos = a.add_batch(fid, idem_key=None, chash="h", form="rays", nrows=4, blob=blob_of(rng))
        before = b.state()[1][0]
        infos.append(a.write_snapshot(fid, seq, pos, saver(data, ext=".x" if i == 1 else "")))
        row = b.field(fid)
        assert (row.snapshot_file, row.snapshot_seq, row.snapshot_position) == (infos[-1].file, seq, pos)
        assert b.snapshot_bytes(row) == infos[-1].bytes == len(data)
        assert b.load_snapshot(row, lambda p, _: p.read_bytes()) == data
        entry = b.read_log(infos[-1].position - 1)[0]
        assert (entry.kind, entry.seq, entry.position) == ("snapshot", seq, infos[-1].position)
        if before.snapshot_file:  # the one replaced is gone
            with pytest.raises(SnapshotGoneError):
                b.load_snapshot(before, lambda p, _: p.read_bytes())
            assert b.snapshot_bytes(before) == 0
    with psycopg.connect(pg_url) as c:
        assert c.execute("SELECT count(*) FROM flatserve.snapshots").fetchone()[0] == 1
        # a writer that died between storing the data and pointing at it
        c.execute("INSERT INTO flatserve.snapshots VALUES ('orphan', %s, 3, 0)", (fid,))
        c.execute("INSERT INTO flatserve.snapshot_chunks VALUES ('orphan', 0, 'abc')")
    assert a.clean_orphans() == 1
    assert b.load_snapshot(b.field(fid), lambda p, _: p.read_bytes()) == b""
    # a field deleted while its snapshot is written: nothing is kept
    def slow_delete(path, _stage):
        b.delete_field(fid)
        path.write_bytes(b"late")
    with pytest.raises(fe.FieldNotFoundError):
        a.write_snapshot(fid, 9, 10**6, slow_delete)
    with psycopg.connect(pg_url) as c:
        assert c.execute("SELECT count(*) FROM flatserve.snapshots").fetchone()[0] == 0
        assert c.execute("SELECT count(*) FROM flatserve.snapshot_chunks").fetchone()[0] == 0


def test_lease_is_exclusive_and_dies_with_its_holder(two, pg_url):
    """One holder at a time across backends; renewals by the holder; a holder whose
    connection dies (a process killed: PostgreSQL ends its session) loses the
    lease at once, whatever its ttl."""
    a, b = two
    assert a.acquire_lease("snapshot", "A", 300)
    assert not b.acquire_lease("snapshot", "B", 300)
    assert a.acquire_lease("snapshot", "A", 300)  # renewal
    assert not a.acquire_lease("snapshot", "other owner, same process", 300)
    with psycopg.connect(pg_url) as c:
        assert c.execute("SELECT owner FROM flatserve.leases WHERE name='snapshot'"
                         ).fetchone() == ("A",)
        a.release_lease("snapshot", "B")  # not B's: no effect
        assert not b.acquire_lease("snapshot", "B", 300)
        a.release_lease("snapshot", "A")
        assert b.acquire_lease("snapshot", "B", 300)
        # B's holder dies (its session ends, as when its process is killed): the one
        # session holding an advisory lock now is B's lease
        n = c.execute("SELECT count(pg_terminate_backend(pid)) FROM pg_locks"
                      " WHERE locktype='advisory' AND granted").fetchone()[0]
    assert n >= 1
    t0 = time.monotonic()
    while not a.acquire_lease("snapshot", "A", 300):  # taken over, no ttl to wait for
        assert time.monotonic() - t0 < 30
        time.sleep(0.05)
    assert not b.acquire_lease("snapshot", "B", 300)
    assert b.acquire_lease("other", "B", 300)  # leases are independent


def test_a_restart_of_postgresql_is_survived(own_pg_cluster):
    """Writes while PostgreSQL is down are refused with StorageUnavailableError (503
    with Retry-After); once it is back the same backend reads, writes and follows
    again, and every acknowledged batch is there."""
    from flatserve.service.http.errors import error_response

    url = own_pg_cluster.create_database("restart")
    a, b = PostgresBackend(url), PostgresBackend(url)
    rng = np.random.default_rng(13)
    try:
        a.check()
        b.check()
        fid, _ = a.create_field("r", {}, BASIS)
        acked = [a.add_batch(fid, idem_key=f"k{i}", chash="h", form="rays", nrows=4,
                             blob=blob_of(rng)) for i in range(5)]
        b.wait_for_change(0.01)
        own_pg_cluster.stop("immediate")  # as a crash
        with pytest.raises(fe.StorageUnavailableError) as err:
            a.add_batch(fid, idem_key="down", chash="h", form="rays", nrows=4, blob=blob_of(rng))
        resp = error_response(err.value)
        assert resp.status_code == 503 and resp.headers["retry-after"] == "1"
        with pytest.raises(fe.StorageUnavailableError):
            b.head()
        b.wait_for_change(0.5)  # the listening connection is gone: no hang, no error
        own_pg_cluster.restart()
        assert [(r.seq, r.position) for r in b.batches(fid)] == acked
        head = b.head()
        for _ in range(3):
            b.wait_for_change(0.5)  # reconnects and listens again
        acked.append(a.add_batch(fid, idem_key="up", chash="h", form="rays", nrows=4,
                                 blob=blob_of(rng)))
        t0 = time.monotonic()
        while b.head() == head:
            b.wait_for_change(60)
            assert time.monotonic() - t0 < 30
        assert [(r.seq, r.position) for r in a.batches(fid)] == acked
    finally:
        a.close()
        b.close()


def test_unreachable_database_and_foreign_schema_are_refused(pg_url, pg_cluster):
    dead = PostgresBackend(f"postgresql://postgres:pw@127.0.0.1:{pg_cluster.port}/nosuchdb",
                           start_timeout=0.5)
    with pytest.raises(fe.StorageError, match=r"cannot reach the database .*\*\*\*"):
        dead.check()
    dead.close()
    be = PostgresBackend(pg_url)
    be.check()
    be.close()
    with psycopg.connect(pg_url) as c:
        c.execute("UPDATE flatserve.meta SET value='99' WHERE key='schema_version'")
    other = PostgresBackend(pg_url)
    with pytest.raises(fe.StorageError, match="schema version 99"):
        other.check()
    other.close()


def test_staging_directories_of_dead_processes_are_removed_at_start(tmp_path):
    """A kill -9 during a snapshot leaves its staging directory behind; the next
    backend on that directory removes those whose lock nobody holds (whatever the
    process ids: other PID namespaces, a restarted PID 1) and keeps a live writer's
    (another process here), young ones without a lock, symlinks and other files."""
    import os
    import subprocess
    import sys
    import time

    from flatserve.service.log.pgsnapshots import STAGE_ORPHAN_AGE
    from flatserve.service.log.pgstorage import PostgresBackend

    holder = ("import fcntl, os, sys, time\n"
              "fd = os.open(sys.argv[1], os.O_RDWR)\n"
              "fcntl.flock(fd, fcntl.LOCK_EX)\n"
              "print('held', flush=True)\n"
              "time.sleep(60)\n")
    live = tmp_path / "flatserve-snap-1-live"
    dead = tmp_path / "flatserve-snap-1-dead"  # the same "pid" as a live one: not asked
    old = tmp_path / "flatserve-snap-k2j3h4g5"
    young = tmp_path / "flatserve-snap-z9y8x7w6"
    other = tmp_path / "unrelated"
    target = tmp_path / "target"
    for d in (dead, live, old, young, other, target):
        d.mkdir()
        (d / "part").write_bytes(b"x" * 10)
    for d in (dead, live):
        (d / ".lock").write_bytes(b"")
    (tmp_path / "flatserve-snap-2-link").symlink_to(target)
    t = time.time() - STAGE_ORPHAN_AGE - 10
    os.utime(old, (t, t))
    proc = subprocess.Popen([sys.executable, "-c", holder, str(live / ".lock")],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        be = PostgresBackend("postgresql://nobody@127.0.0.1:1/none", tmp_dir=tmp_path)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            [p.name for p in (live, young, other, target)] + ["flatserve-snap-2-link"])
        assert (target / "part").exists()
        # a backend's own staging directory is locked until it is done with it
        d = be._stage()
        PostgresBackend("postgresql://nobody@127.0.0.1:1/none", tmp_dir=tmp_path).close()
        assert d.is_dir()
        be._unstage(d)
        assert not d.exists()
        be.close()
    finally:
        proc.kill()
        proc.wait()
    PostgresBackend("postgresql://nobody@127.0.0.1:1/none", tmp_dir=tmp_path).close()
    assert not live.exists()  # its holder is gone


def test_a_lapsed_lease_is_not_renewed_even_when_free_again(two, pg_url):
    """The writer's lease session ends (a restart, a terminated backend); another
    replica takes the lease, cleans up what no field points at (the writer's stored
    snapshot data) and releases it. The writer's renewal must say the lease lapsed
    (acquire_lease would take the free lock again), and pointing the field at data
    that was removed is refused: the field keeps no dangling snapshot."""
    a, b = two
    fid, _ = a.create_field("f", {"k": 1}, BASIS)
    lease = snapshot_lease(fid)
    assert a.acquire_lease(lease, "A", 300) and a.renew_lease(lease, "A", 300)
    assert not a.renew_lease(lease, "B", 300) and not b.renew_lease(lease, "A", 300)

    def lose_it():
        with psycopg.connect(pg_url) as c:
            c.execute("SELECT pg_terminate_backend(pid) FROM pg_locks"
                      " WHERE locktype='advisory' AND granted")
        t0 = time.monotonic()
        while not b.acquire_lease(lease, "B", 300):  # free once PostgreSQL saw it end
            assert time.monotonic() - t0 < 30
            time.sleep(0.05)
        b.release_lease(lease, "B")
        assert b.clean_orphans() == 1  # the writer's data, pointed at by no field

    def check():
        lose_it()
        if not a.renew_lease(lease, "A", 300):
            raise RuntimeError("lease lapsed")

    with pytest.raises(RuntimeError, match="lapsed"):
        a.write_snapshot(fid, 0, 0, save_bytes(b"snap" * 100), check)
    assert a.field(fid).snapshot_file is None
    # without the check: the removed data is noticed in the pointing transaction
    assert a.acquire_lease(lease, "A", 300)

    with pytest.raises(fe.StorageError, match="removed before the field pointed"):
        a.write_snapshot(fid, 0, 0, save_bytes(b"snap" * 100), lose_it)
    assert a.field(fid).snapshot_file is None


def test_clean_up_takes_each_fields_lease(two):
    check_clean_up_under_field_leases(two[0])
