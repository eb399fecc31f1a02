"""Replicas on one shared log, with REAL server processes: a write through one is
read through another with its position; replicas at one position answer bit for
bit alike; kill -9 of a replica (during uploads, while writing a snapshot) loses
nothing acknowledged; ``serve --processes 2`` shares one port and one data
directory, and an unrelated server on it is still refused."""
from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from flatserve.client import Client
from flatserve.field import Field
from flatserve.service.rooms import specs
from flatserve.service.log.backend import snapshot_lease
from flatserve.service.log.blobs import content_hash, pack_arrays
from flatserve.service.status import FieldNotFoundError, NotReadyError
from flatserve.service.log.storage import DB_NAME, lock_data_dir
from tests.harness.fields import DEFAULT, KINDS, ONE_CHART, add_rays, paper_rays, query_rays
from tests.harness.process import ServerProcess, children, kill9_and_await_restart
from tests.harness.service import (assert_data_dir_refused, started, upload_until_stopped,
                                   verify_stored)

C = 2


def _ref(channels=C):
    return Field(specs.build_basis(None, 1, 3), channels=channels)


def _answers(c, name, probe, pos, weights=True):
    """Every array of a query (with weights unless ``weights`` is False: an atlas
    field blends charts and returns none), read at log position ``pos``."""
    r = c.query_rays(name, *probe, weights=weights, min_position=pos)
    return (r.values, r.inside, r.status) + ((r.ids, r.weights) if weights else ())


def _identical(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)  # NaN == NaN here, bit for bit otherwise


@pytest.fixture
def group(tmp_path):
    """``start(log_name, **options) -> ServerProcess``: replicas of one group on
    ``tmp_path / "data"`` (they share the data directory's lock, as the processes of
    ``serve --processes N`` do). Every one is killed at the end."""
    data = tmp_path / "data"
    fd = lock_data_dir(data)
    procs = []

    def start(name, **kw):
        kw.setdefault("snapshot_every", 0)
        p = ServerProcess(data, tmp_path / f"{name}.log", lock_fd=fd, **kw)
        procs.append(p)
        return p

    start.data = data
    start.tmp = tmp_path
    try:
        yield start
    finally:
        for p in procs:
            p.kill9()
        os.close(fd)


def test_write_through_one_replica_read_through_the_other(group, rng):
    a, b = group("a"), group("b")
    a.wait_ready()
    b.wait_ready()
    ref = _ref()
    with Client(a.url) as ca, Client(b.url) as cb:
        info = ca.create_field("f", channels=C, basis=ONE_CHART)  # compared with ids, weights
        assert cb.describe("f", min_position=info["position"])["nsamples"] == 0
        probe = paper_rays(rng, 300)
        for i, wait in enumerate((False, True, False)):
            o, v = paper_rays(rng, 2000)
            val = rng.normal(size=(2000, C))
            ref.add_rays(o, v, val)
            rep = (ca if i % 2 == 0 else cb).upload_rays("f", o, v, val, wait=wait,
                                                       idempotency_key=f"k{i}")
            other = cb if i % 2 == 0 else ca
            got = other.query_rays("f", *probe, weights=True, min_position=rep["position"])
            want = ref.query_rays(*probe, return_weights=True)
            np.testing.assert_array_equal(got.inside, want.inside)
            np.testing.assert_array_equal(got.ids, want.ids)
            np.testing.assert_array_equal(got.values, want.values)
            d = other.describe("f", min_position=rep["position"])
            assert d["nsamples"] == ref.nsamples and d["indexed_batch"] == i + 1
        # a retry through the other replica is recognised (the key is the database's)
        again = cb.upload_rays("f", o, v, val, idempotency_key="k2")
        assert again["replayed"] and again["batch"] == 3 and again["position"] == rep["position"]
        assert len(ca.batches("f")) == 3
        # a delete through one replica is seen by the other at its position
        cb.delete_field("f")
        pos = int(cb.last_response.headers["Flatserve-Position"])
        with pytest.raises(FieldNotFoundError):
            ca.describe("f", min_position=pos)
        # lag is reported by both
        for srv in (a, b):
            r = srv.readyz()
            assert r["position"] == r["head"] >= pos and r["lag_entries"] == 0
        assert "flatserve_log_lag_seconds" in ca.metrics()


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_replicas_at_the_same_position_answer_bit_identically(group, rng, kind):
    """Writes through both replicas, duplicates included; a third replica started
    afterwards restores from the log; all three answer alike, bit for bit."""
    a, b = group("a", insert_slice_rows=700), group("b", insert_slice_rows=700)
    a.wait_ready()
    b.wait_ready()
    with Client(a.url) as ca, Client(b.url) as cb:
        ca.create_field("f", channels=C, basis=kind.basis)
        sent = []
        for i in range(6):
            o, v = paper_rays(rng, 1500)
            if i >= 3:  # the same flats again, other values: duplicates
                o, v = sent[i - 3]
            sent.append((o, v))
            rep = (ca, cb)[i % 2].upload_rays("f", o, v, rng.normal(size=(1500, C)),
                                              wait=bool(i % 3))
        assert rep["duplicates"] and rep["duplicates"] > 0
        pos = rep["position"]
        probe = paper_rays(rng, 2000)
        w = not kind.atlas
        want = _answers(ca, "f", probe, pos, w)
        _identical(_answers(cb, "f", probe, pos, w), want)
        late = group("late", insert_slice_rows=700)
        late.wait_ready()
        with Client(late.url) as cl:
            _identical(_answers(cl, "f", probe, pos, w), want)
            assert cl.describe("f")["nsamples"] == ca.describe("f")["nsamples"]


def test_a_read_waits_a_bounded_time_for_a_position_then_503(make_app, rng, monkeypatch):
    """A position not yet applied here: 503 with Retry-After after read_wait_timeout
    (the follower is held, as a replica behind would be); a position beyond the
    log's head was never returned by a write: 422 at once."""
    from flatserve.service.rooms import applier as applier_mod

    gate = threading.Event()
    monkeypatch.setattr(applier_mod.LogApplier, "_before_index",
                        staticmethod(lambda e, seq: gate.wait(30)))
    tc, c = started(make_app(read_wait_timeout=0.2))
    try:
        info = c.create_field("f")
        o, v = paper_rays(rng, 300)
        rep = c.upload_rays("f", o, v, np.ones(300), wait=False)
        r = tc.get("/v1/fields/f", params={"min_position": rep["position"]})
        assert r.status_code == 503 and r.headers["retry-after"] == "1", r.text
        assert "not yet" in r.json()["detail"]
        with pytest.raises(NotReadyError, match="not yet"):  # 503: the client's class
            c.query_rays("f", o[:3], v[:3], min_position=rep["position"])
        assert c.query_rays("f", o[:3], v[:3], min_position=info["position"]).values.shape \
            == (3, 1)
        r = tc.post("/v1/fields/f/query", params={"min_position": rep["position"] + 1},
                    json={"origins": o[:3].tolist(), "directions": v[:3].tolist()})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "min_position"
        gate.set()
        got = c.query_rays("f", o[:3], v[:3], min_position=rep["position"])
        assert got.inside.any()
        spec = tc.get("/openapi.json").json()
        params = spec["paths"]["/v1/fields/{name}/query"]["post"]["parameters"]
        assert "min_position" in [p["name"] for p in params]
    finally:
        gate.set()
        tc.__exit__(None, None, None)


def test_kill9_of_a_replica_during_uploads_loses_nothing(group):
    rng = np.random.default_rng(11)
    a, b = group("a"), group("b")
    a.wait_ready()
    b.wait_ready()
    sent, acked = {}, {}
    probe = paper_rays(rng, 300)
    with Client(a.url) as c:
        c.create_field(str(DEFAULT), channels=1)  # the default field: a covering atlas
    for rnd in range(3):
        stop = threading.Event()
        ts = [threading.Thread(target=upload_until_stopped,
                               args=(srv.url, str(DEFAULT), f"{tag}{rnd}",
                                     np.random.default_rng(10 * rnd + k), sent, acked, stop),
                               kwargs={"max_rows": 1500, "binary_every": 3,
                                       "survive": tag == "b"})
              for k, (tag, srv) in enumerate((("a", a), ("b", b)))]
        for t in ts:
            t.start()
        time.sleep(float(rng.uniform(0.5, 1.5)))
        a.kill9()
        # b keeps serving writes and reads while a is down
        n_before = sum(k.startswith(f"b{rnd}") for k in acked)
        time.sleep(0.5)
        with Client(b.url) as cb:
            cb.query_rays(str(DEFAULT), *probe)
        stop.set()
        for t in ts:
            t.join(60)
        assert sum(k.startswith(f"b{rnd}") for k in acked) > n_before
        a = group(f"a{rnd}")  # the restarted replica catches up
        a.wait_ready()
        head = max(r["position"] for r in acked.values())
        with Client(a.url) as ca:
            ca.describe(str(DEFAULT), min_position=head)
    nb = verify_stored(b.url, DEFAULT, sent, acked, probe)
    na = verify_stored(a.url, DEFAULT, sent, acked, probe)
    assert na == nb and acked


def test_kill9_of_the_replica_writing_a_snapshot(group, rng):
    a = group("a", snapshot_lease_seconds=5)
    b = group("b", snapshot_lease_seconds=5)
    a.wait_ready()
    b.wait_ready()
    snaps = group.data / "snapshots"
    with Client(a.url, timeout=120) as ca, Client(b.url, timeout=120) as cb:
        ca.create_field("f", channels=1)
        for _ in range(4):
            o, v = paper_rays(rng, 15_000)
            rep = ca.upload_rays("f", o, v, rng.uniform(size=15_000))
        cb.describe("f", min_position=rep["position"])
        def snapshot_on_a():
            try:
                httpx.post(a.url + "/v1/fields/f/snapshot", timeout=120)
            except httpx.TransportError:  # killed while it writes: the point of the test
                pass

        hit = threading.Thread(target=snapshot_on_a)
        hit.start()
        end = time.monotonic() + 60
        while time.monotonic() < end and not any(p.name.startswith(".tmp-")
                                                 for p in snaps.iterdir()):
            pass
        assert any(p.name.startswith(".tmp-") for p in snaps.iterdir()), "no snapshot seen"
        a.kill9()
        hit.join(60)
        # the other replica serves reads and writes, and takes over the snapshot lease
        # of the dead writer (a dead process of this machine: no wait for its expiry)
        o, v = paper_rays(rng, 500)
        rep = cb.upload_rays("f", o, v, rng.uniform(size=500))
        probe = paper_rays(rng, 300)
        want = _answers(cb, "f", probe, rep["position"], weights=False)  # default: atlas
        r = httpx.post(b.url + "/v1/fields/f/snapshot", timeout=120)
        assert r.status_code == 200 and r.json()["batch"] == 5, r.text
        a = group("a2", snapshot_lease_seconds=5)
        a.wait_ready()
    with Client(a.url) as ca:
        _identical(_answers(ca, "f", probe, rep["position"], weights=False), want)
    # the dead writer's file and its parts' staging directory: gone
    assert [p.name for p in snaps.iterdir() if p.is_file()] == ["f1-s5.snap"]
    parts = list((snaps / "parts").iterdir())
    assert parts and all(p.is_file() and p.name.startswith("p1-") for p in parts), parts
    assert "snapshot after batch 5 loaded" in (group.tmp / "a2.log").read_text()


def test_processes_2_share_one_port_and_one_data_dir(tmp_path, rng):
    data = tmp_path / "data"
    with ServerProcess(data, tmp_path / "s.log", processes=2, snapshot_every=0) as srv:
        srv.wait_ready()
        kids = children(srv.proc.pid)
        assert len(kids) == 2
        # an unrelated server on the directory is refused, naming the holder
        assert_data_dir_refused(data, srv.proc.pid)
        ref = DEFAULT.reference(1)
        with Client(srv.url) as c:
            c.create_field("f", channels=1)
        seen = set()
        for i in range(12):  # a new connection each time: either replica answers
            o, v = paper_rays(rng, 400)
            val = rng.uniform(size=400)
            add_rays(ref, o, v, val)
            with Client(srv.url) as c:
                rep = c.upload_rays("f", o, v, val, wait=bool(i % 2))
            probe = paper_rays(rng, 50)
            with Client(srv.url) as c:
                got = c.query_rays("f", *probe, min_position=rep["position"])
                seen.add(httpx.get(srv.url + "/readyz").json()["pid"])
            np.testing.assert_array_equal(got.values, query_rays(ref, *probe).values)
        assert seen <= set(kids)
        # a replica killed is restarted by the supervisor and catches up
        kill9_and_await_restart(srv.proc.pid, kids[0], 2)
        for _ in range(20):
            with Client(srv.url) as c:
                c.wait_ready(60)
                assert c.describe("f", min_position=rep["position"])["nsamples"] == ref.nsamples


def test_schema_2_data_dir_opens_with_every_batch(tmp_path, make_app, rng):
    """A data directory written before the log (schema 2) is migrated: the log is
    backfilled and every batch restored."""
    from flatserve.service.log.storage import _SCHEMA_V2

    data = tmp_path / "data"
    data.mkdir()
    basis = specs.build_basis(None, 1, 3)
    db = sqlite3.connect(data / DB_NAME)
    db.executescript(_SCHEMA_V2)
    ref = {}
    for fid, name in ((1, "g"), (2, "f")):
        ref[name] = _ref(1)
        db.execute("INSERT INTO fields(id, name, spec, basis, created) VALUES (?, ?, ?, ?, ?)",
                   (fid, name, '{"k": 1, "d": 3, "channels": 1, "basis": {}}',
                    pack_arrays({"Q": basis.Q, "r": basis.r}), 1.0))
        for seq in (1, 2, 3):
            o, v = paper_rays(rng, 300)
            val = rng.uniform(size=(300, 1))
            ref[name].add_rays(o, v, val)
            arrays = {"origins": o, "directions": v, "values": val}
            db.execute("INSERT INTO batches(field_id, seq, idem_key, content_hash, form, nrows,"
                       " arrays, result, created) VALUES (?, ?, ?, ?, 'rays', 300, ?, 'null', ?)",
                       (fid, seq, f"{name}{seq}", content_hash("rays", arrays),
                        pack_arrays(arrays), 2.0 + seq))
    db.execute("PRAGMA user_version=2")
    db.commit()
    db.close()
    tc, c = started(make_app(data_dir=data))
    try:
        probe = paper_rays(rng, 200)
        for name in ("f", "g"):
            assert [b["batch"] for b in c.batches(name)] == [1, 2, 3]
            np.testing.assert_array_equal(c.query_rays(name, *probe).values,
                                          ref[name].query_rays(*probe).values)
        rep = c.upload_rays("f", *paper_rays(rng, 10), np.ones(10))
        assert rep["batch"] == 4 and rep["position"] == 9  # 2 creates + 6 batches before it
    finally:
        tc.__exit__(None, None, None)
    db = sqlite3.connect(data / DB_NAME)
    assert db.execute("PRAGMA user_version").fetchone()[0] == 3
    kinds = db.execute("SELECT kind, field_id, seq FROM log ORDER BY position").fetchall()
    assert kinds[:4] == [("create", 1, 0), ("batch", 1, 1), ("batch", 1, 2), ("batch", 1, 3)]
    db.close()


def test_one_snapshot_writer_at_a_time(make_app, rng):
    """The snapshot lease: while another live replica holds it, a snapshot is refused
    (503, Retry-After) and a background one is put off; released, it goes ahead."""
    import socket

    tc, c = started(make_app())
    try:
        c.create_field("f")
        c.upload_rays("f", *paper_rays(rng, 300), np.ones(300))
        storage = tc.app.state.rooms.storage
        lease = snapshot_lease(tc.app.state.rooms.catalogue.get("f").id)
        other = f"{socket.gethostname()}:{os.getpid()}:another-replica"  # alive: this pid
        assert storage.acquire_lease(lease, other, 60)
        r = tc.post("/v1/fields/f/snapshot")
        assert r.status_code == 503 and "another replica" in r.text and r.headers["retry-after"]
        assert c.describe("f")["storage"]["snapshot_batch"] == 0
        storage.release_lease(lease, other)
        assert c.snapshot("f")["batch"] == 1
        assert storage.acquire_lease(lease, other, 60)  # released after the write
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_snapshot_whose_lease_is_taken_meanwhile_is_abandoned(make_app, rng, request,
                                                                 backend):
    """The writer's lease lost while it writes (a pause longer than the lease, a
    database connection dropped): another replica may hold it and remove what no
    field points at, so the writer must not point the field at its snapshot. It
    answers 503 and leaves nothing stored; once the lease is free again a snapshot
    is written."""
    import socket

    opts = {} if backend == "sqlite" else {"database_url": request.getfixturevalue("pg_url")}
    tc, c = started(make_app(**opts))
    try:
        c.create_field("f")
        c.upload_rays("f", *paper_rays(rng, 300), np.ones(300))
        reg = tc.app.state.rooms
        storage = reg.storage
        write = storage.write_snapshot
        other = f"{socket.gethostname()}:{os.getpid()}:another-replica"  # alive: this pid
        lease = snapshot_lease(reg.catalogue.get("f").id)

        def stolen_write(field_id, seq, position, save, check=None):
            def save_then_lose(path, stage):
                keys = save(path, stage)
                storage.release_lease(lease, reg.snapshots.owner)  # as if it had expired ...
                assert storage.acquire_lease(lease, other, 60)  # ... and been taken
                return keys
            return write(field_id, seq, position, save_then_lose, check)

        storage.write_snapshot = stolen_write
        r = tc.post("/v1/fields/f/snapshot")
        assert r.status_code == 503 and "lease was lost" in r.text, r.text
        assert c.describe("f")["storage"]["snapshot_batch"] == 0
        assert storage.clean_orphans() == 0  # nothing of it was left stored
        storage.write_snapshot = write
        storage.release_lease(lease, other)
        assert c.snapshot("f")["batch"] == 1
    finally:
        tc.__exit__(None, None, None)


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_snapshot_being_stored_does_not_hold_up_the_follower(make_app, rng, request,
                                                               backend):
    """The field is serialised under its lock; storing the snapshot (the database
    part: SQLite's commit, PostgreSQL's chunks) runs outside it: held there, the
    follower still applies a batch of the same field and a wait=true upload to
    another field answers; the snapshot recorded is the state at its batch (a
    restart from it answers as before)."""
    opts = {} if backend == "sqlite" else {"database_url": request.getfixturevalue("pg_url")}
    tc, c = started(make_app(**opts))
    try:
        c.create_field("f")
        c.create_field("g")
        o, v = paper_rays(rng, 400)
        c.upload_rays("f", o[:200], v[:200], np.ones(200))
        n1 = c.describe("f")["nsamples"]
        reg = tc.app.state.rooms
        storage = reg.storage
        write = storage.write_snapshot
        stored, gate = threading.Event(), threading.Event()

        def held_write(field_id, seq, position, save, check=None):
            def save_then_hold(path, stage):
                keys = save(path, stage)
                stored.set()
                gate.wait(60)  # the database part of the write, held
                return keys
            return write(field_id, seq, position, save_then_hold, check)

        storage.write_snapshot = held_write
        out = {}
        snap = threading.Thread(target=lambda: out.update(
            reg.snapshots.snapshot(reg.catalogue.get("f")).model_dump()))
        snap.start()
        assert stored.wait(30)
        rep_f = c.upload_rays("f", o[200:300], v[200:300], np.ones(100), wait=False)
        done = threading.Event()
        got = {}

        def upload_g():
            got.update(c.upload_rays("g", o[300:], v[300:], np.ones(100)))
            done.set()

        th = threading.Thread(target=upload_g, daemon=True)
        th.start()
        finished = done.wait(30)
        gate.set()
        snap.join(60)
        th.join(60)
        assert finished, "the follower waited for the snapshot's database part"
        assert got["indexed"] and reg.follower.applied >= rep_f["position"]
        assert out["batch"] == 1  # the state when serialised, not batch 2 applied later
        d = c.describe("f")
        assert d["storage"]["snapshot_batch"] == 1 and d["nsamples"] > n1
        e = reg.catalogue.get("f")
        row = storage.field(e.id)
        assert storage.load_snapshot(row, e.spec.load_field).nsamples == n1
        probe = (o[:50], v[:50])
        before = c.query_rays("f", *probe)
    finally:
        gate.set()
        tc.__exit__(None, None, None)
    tc, c = started(make_app(**opts))  # restored from the snapshot at batch 1 + batch 2
    try:
        after = c.query_rays("f", *probe)
        assert c.describe("f")["nsamples"] == d["nsamples"]
        np.testing.assert_array_equal(after.inside, before.inside)
        np.testing.assert_allclose(after.values, before.values, rtol=1e-12, atol=1e-12)
    finally:
        tc.__exit__(None, None, None)


def test_a_child_whose_supervisor_died_before_its_death_signal_was_set_exits():
    """A replica started just as its supervisor dies: the request to die with the
    parent (PR_SET_PDEATHSIG) would never fire, so the child checks that its parent is
    still the supervisor and exits otherwise."""
    code = ("import os, sys\n"
            "from flatserve.service.supervisor import _die_with_parent\n"
            "_die_with_parent(os.getppid())\n"  # its parent is there: goes on
            "print('alive', flush=True)\n"
            "_die_with_parent(int(sys.argv[1]))\n"  # a parent it no longer has: exits
            "print('still here', flush=True)\n")
    out = subprocess.run([sys.executable, "-c", code, str(os.getpid() + 10**6)],
                         capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["alive"] and out.returncode == 1, out


def test_children_import_the_supervisors_installation_from_any_directory(tmp_path, rng):
    """``flatserve serve --processes 2`` started in a directory holding another
    ``flatserve`` package (a source checkout without the built extension): the
    children import the installation the supervisor runs, not that directory's
    (which ``python -m`` would put first on ``sys.path``), and serve."""
    checkout = tmp_path / "checkout"
    (checkout / "flatserve" / "service").mkdir(parents=True)
    for init in (checkout / "flatserve" / "__init__.py",
                 checkout / "flatserve" / "service" / "__init__.py"):
        init.write_text("raise ImportError('a source tree without its built extension')\n")
    script = os.path.join(os.path.dirname(sys.executable), "flatserve")
    assert os.path.exists(script)  # the installed console script (sys.path[0]: its bin/)
    with ServerProcess(tmp_path / "data", tmp_path / "s.log", command=[script, "serve"],
                       cwd=checkout, processes=2, snapshot_every=0) as srv:
        srv.wait_ready(timeout=120)
        assert len(children(srv.proc.pid)) == 2
        with Client(srv.url) as c:
            c.create_field("f", channels=1)
            o, v = paper_rays(rng, 200)
            rep = c.upload_rays("f", o, v, rng.uniform(size=200))
            assert rep["accepted"] == 200
    assert "source tree without" not in (tmp_path / "s.log").read_text()


def test_a_restarted_replica_takes_connections_only_once_ready(tmp_path, rng):
    """``--processes 2``: after kill -9 of one replica, its successor restores the
    field (seconds) before it accepts a connection on the shared socket, so every
    request on a new connection meanwhile is answered by the ready sibling: no
    ``503 field is still loading``."""
    with ServerProcess(tmp_path / "data", tmp_path / "s.log", processes=2,
                       snapshot_every=0) as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            c.create_field("f", channels=1, basis=ONE_CHART)
            for _ in range(2):
                o, v = paper_rays(rng, 25_000)
                rep = c.upload_rays("f", o, v, rng.uniform(size=25_000))
        kids = children(srv.proc.pid)
        assert len(kids) == 2
        for _ in range(20):  # both replicas have applied every batch
            with Client(srv.url) as c:
                info = c.describe("f", min_position=rep["position"])
                assert info["pending_samples"] == 0
        os.kill(kids[0], 9)
        probe = paper_rays(rng, 20)
        body = {"origins": probe[0].tolist(), "directions": probe[1].tolist()}
        statuses, end, restored = [], time.monotonic() + 120, False
        log = tmp_path / "s.log"
        while time.monotonic() < end and not restored:
            # a new connection each time: the kernel hands it to a replica accepting
            r = httpx.post(srv.url + "/v1/fields/f/query", json=body, timeout=30,
                           headers={"connection": "close"})
            statuses.append(r.status_code)
            now = [k for k in children(srv.proc.pid) if k not in kids]
            restored = bool(now) and "': restored, " in \
                log.read_text().partition(f"started (pid {now[0]})")[2]
        assert restored, "the restarted replica never became ready"
        assert len(statuses) >= 5  # requests were made while it restored
        assert set(statuses) == {200}, statuses
