"""Replicas on PostgreSQL, with REAL server processes and a real PostgreSQL (a
throwaway cluster): two servers on one database, a write through one and a read
through the other with the consistency token (``min_position``); kill -9 of
either during uploads; PostgreSQL stopped and restarted under running replicas;
kill -9 of a replica writing a snapshot; a replica started on an empty machine
with only the database URL. After each: every acknowledged batch is stored once
and whole, and every replica answers exactly as a field built in-process from
the stored batches, in their order. The fields are single charts (compared sample
ids and weights included); the default (atlas) field goes through the same log in
tests/service/test_service_replicas.py."""
from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path

import numpy as np
import psycopg
import pytest

from flatserve.client import Client, ServiceError
from flatserve.field import Field
from flatserve.service.rooms import specs
from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.process import ServerProcess
from tests.harness.service import snapshot_soon

FIELD = "pg"


class Replicas:
    """Server processes on one database, each on its own empty data directory;
    all killed (kill -9) when the test ends."""

    def __init__(self, tmp: Path, url: str, stack: contextlib.ExitStack, **options):
        self.tmp, self.url, self.stack, self.options = tmp, url, stack, options
        self.n = 0

    def start(self, **more) -> ServerProcess:
        self.n += 1
        d = self.tmp / f"replica{self.n}"
        srv = self.stack.enter_context(ServerProcess(
            d, self.tmp / f"replica{self.n}.log", database_url=self.url,
            **{**self.options, **more}))
        srv.wait_ready(120)
        return srv

    def pair_with_field(self) -> tuple[ServerProcess, ServerProcess]:
        """Two replicas, with the test's (empty, ONE_CHART) field created through the first."""
        a, b = self.start(), self.start()
        with Client(a.url, retries=0) as c:
            c.create_field(FIELD, channels=2, basis=ONE_CHART)
        return a, b

    def logs(self) -> str:
        return "\n".join(f"--- replica{i} ---\n" + (self.tmp / f"replica{i}.log").read_text()[-3000:]
                         for i in range(1, self.n + 1))


@pytest.fixture
def replicas(tmp_path, pg_url):
    with contextlib.ExitStack() as stack:
        yield lambda url=pg_url, **opt: Replicas(tmp_path, url, stack, **{"snapshot_every": 0, **opt})


class Book:
    """What the clients sent and what was acknowledged (thread-safe)."""

    def __init__(self):
        self.sent: dict[str, tuple] = {}
        self.acked: dict[str, dict] = {}
        self.lock = threading.Lock()

    def batch(self, rng, key: str, n: int | None = None):
        n = n or int(rng.integers(200, 2500))
        o, d = paper_rays(rng, n)
        v = rng.uniform(size=(n, 2))
        with self.lock:
            self.sent[key] = (o, d, v)
        return o, d, v

    def ack(self, key: str, report: dict) -> None:
        with self.lock:
            self.acked[key] = report

    def upload(self, client, rng, key: str, n: int | None = None) -> dict:
        """Send a new batch under ``key`` (its Idempotency-Key) and book its answer."""
        report = client.upload_rays(FIELD, *self.batch(rng, key, n), idempotency_key=key)
        self.ack(key, report)
        return report

    def uploads(self, client, rng, prefix: str, count: int, n: int) -> None:
        """``count`` new batches of ``n`` rows, keys ``prefix0``, ``prefix1``, ..."""
        for i in range(count):
            self.upload(client, rng, f"{prefix}{i}", n)


def reference(book: Book, stored: list[dict]) -> Field:
    """The field built in-process from the stored batches in their order."""
    ref = Field(specs.build_basis(None, 1, 3), channels=2)  # as ONE_CHART fields
    for b in stored:
        o, d, v = book.sent[b["idempotency_key"]]
        assert b["rows"] == len(o), "a batch was stored half"
        res = ref.add_rays(o, d, v)
        if b["idempotency_key"] in book.acked:
            assert book.acked[b["idempotency_key"]]["accepted"] == res.accepted
    return ref


def check_replicas(book: Book, urls: list[str], probe, min_position: int | None = None) -> int:
    """Every acknowledged batch stored once and whole; every replica (once at the
    log's head) answers as the in-process reference. Returns the head position."""
    with Client(urls[0], retries=0) as c:
        stored = c.batches(FIELD)
    keys = [b["idempotency_key"] for b in stored]
    assert len(keys) == len(set(keys)), "a batch was stored twice"
    assert [b["batch"] for b in stored] == list(range(1, len(stored) + 1))
    lost = set(book.acked) - set(keys)
    assert not lost, f"acknowledged batches lost: {sorted(lost)}"
    for k, rep in book.acked.items():
        assert rep["batch"] == stored[keys.index(k)]["batch"]
    ref = reference(book, stored)
    want = ref.query_rays(*probe, return_weights=True)
    head = min_position if min_position is not None else max(
        [0] + [r["position"] for r in book.acked.values()])
    for url in urls:
        with Client(url, retries=0) as c:
            info = c.describe(FIELD, min_position=head)
            assert info["nsamples"] == ref.nsamples, url
            got = c.query_rays(FIELD, *probe, weights=True, min_position=head)
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_array_equal(got.ids, want.ids)
        np.testing.assert_array_equal(got.values, want.values)  # bit-identical
    return head


def test_write_through_one_read_through_the_other(replicas, rng):
    group = replicas()
    a, b = group.pair_with_field()
    book = Book()
    probe = paper_rays(rng, 500)
    with Client(a.url, retries=0) as ca, Client(b.url, retries=0) as cb:
        for i in range(6):
            writer, reader = (ca, cb) if i % 2 == 0 else (cb, ca)  # any replica takes writes
            o, d, v = book.batch(rng, f"k{i}", 1500)
            rep = writer.upload_rays(FIELD, o, d, v, idempotency_key=f"k{i}", wait=bool(i % 3))
            book.ack(f"k{i}", rep)
            # read-your-writes on the other replica: at once, with the token
            got = reader.query_rays(FIELD, o, d, min_position=rep["position"])
            mine = np.ones(len(o), bool)
            mine[rep["rejected"]] = False
            hit = mine & got.inside
            assert hit.mean() > 0.9
            np.testing.assert_allclose(got.values[hit], v[hit], rtol=0, atol=1e-9)
            info = reader.describe(FIELD, min_position=rep["position"])
            assert info["position"] >= rep["position"]
            if rep["indexed"]:
                assert info["nsamples"] == rep["nsamples"]
        # a retry of a stored batch through the other replica is a replay
        again = cb.upload_rays(FIELD, *book.sent["k0"], idempotency_key="k0")
        assert again["replayed"] and again["batch"] == book.acked["k0"]["batch"]
    check_replicas(book, [a.url, b.url], probe)


def _writer(url, rng, book, prefix, stop, errors, n_max=400):
    """Uploads until ``stop`` (or the server dies: it stops, leaving the batch in
    flight unacknowledged); every other batch acknowledged before indexing."""
    with Client(url, retries=0, timeout=60) as c:
        for i in range(n_max):
            if stop.is_set():
                return
            key = f"{prefix}{i}"
            o, d, v = book.batch(rng, key)
            try:
                book.ack(key, c.upload_rays(FIELD, o, d, v, idempotency_key=key, wait=bool(i % 2)))
            except ServiceError as exc:
                errors.append((key, exc.status, c.last_response.headers.get("retry-after")))
                if exc.status != 503:
                    raise
            except Exception:
                return  # the server died under us


def _retry_unacked(url, book):
    """The client's side of a kill: each batch in flight is sent again with its key
    (to another replica); stored or not, it ends up stored exactly once."""
    with Client(url, retries=0, timeout=60) as c:
        for key in sorted(set(book.sent) - set(book.acked)):
            book.ack(key, c.upload_rays(FIELD, *book.sent[key], idempotency_key=key))


@pytest.mark.parametrize("victim", ["a", "b"])  # either replica (both take writes)
def test_kill9_of_either_replica_during_uploads_loses_nothing(replicas, rng, victim):
    group = replicas()
    a, b = group.pair_with_field()
    book = Book()
    probe = paper_rays(rng, 400)
    for rnd in range(2):
        stop = threading.Event()
        errors: list = []
        ts = [threading.Thread(target=_writer, args=(srv.url, np.random.default_rng(10 * rnd + j),
                                                     book, f"r{rnd}{name}-", stop, errors))
              for j, (name, srv) in enumerate([("a", a), ("b", b)])]
        for t in ts:
            t.start()
        while len(book.acked) < 6 * (rnd + 1):  # uploads are flowing through both
            time.sleep(0.05)
        time.sleep(float(rng.uniform(0, 0.5)))
        dead = a if victim == "a" else b
        dead.kill9()
        survivor = b if dead is a else a
        # the survivor keeps taking writes and answering reads meanwhile
        with Client(survivor.url, retries=0) as c:
            book.upload(c, rng, f"during{rnd}")
            assert c.query_rays(FIELD, *probe).inside.any()
        stop.set()
        for t in ts:
            t.join(120)
        assert not errors, errors
        _retry_unacked(survivor.url, book)
        restarted = group.start()  # an empty data directory: it catches up from the log
        if dead is a:
            a = restarted
        else:
            b = restarted
        check_replicas(book, [a.url, b.url], probe)


def test_postgresql_restart_while_replicas_run(tmp_path, own_pg_cluster, rng):
    url = own_pg_cluster.create_database("restart")
    with contextlib.ExitStack() as stack:
        group = Replicas(tmp_path, url, stack, snapshot_every=0)
        a, b = group.pair_with_field()
        book = Book()
        probe = paper_rays(rng, 400)
        with Client(a.url, retries=0) as ca, Client(b.url, retries=0) as cb:
            for i in range(4):
                key = f"before{i}"
                book.ack(key, (ca if i % 2 else cb).upload_rays(FIELD, *book.batch(rng, key),
                                                                idempotency_key=key))
            head = check_replicas(book, [a.url, b.url], probe)
            before = cb.query_rays(FIELD, *probe)

            own_pg_cluster.stop("immediate")  # as a crash of the database
            # writes are refused with 503 + Retry-After (nothing half-done) ...
            for c, key in ((ca, "down-a"), (cb, "down-b")):
                with pytest.raises(ServiceError) as err:
                    c.upload_rays(FIELD, *book.batch(rng, key), idempotency_key=key)
                assert err.value.status == 503, err.value
                assert c.last_response.headers["retry-after"] == "1"
            # ... reads go on from memory, up to the position the replica has
            got = ca.query_rays(FIELD, *probe, min_position=head)
            np.testing.assert_array_equal(got.values, before.values)

            # writers keep trying through the restart, as a client following Retry-After
            stop = threading.Event()
            seen: list = []
            refused = [threading.Event(), threading.Event()]

            def writer(c, prefix, r, refused):
                i = 0
                while not stop.is_set() or i < 3:
                    key = f"{prefix}{i}"
                    args = book.sent.get(key) or book.batch(r, key)
                    try:
                        book.ack(key, c.upload_rays(FIELD, *args, idempotency_key=key))
                        i += 1
                    except ServiceError as exc:
                        seen.append((exc.status, c.last_response.headers.get("retry-after")))
                        refused.set()
                        time.sleep(0.25)

            with Client(a.url, retries=0, timeout=60) as wa, Client(b.url, retries=0, timeout=60) as wb:
                ts = [threading.Thread(target=writer, args=(w, p, np.random.default_rng(s), ev))
                      for w, p, s, ev in ((wa, "wa", 1, refused[0]), (wb, "wb", 2, refused[1]))]
                for t in ts:
                    t.start()
                for ev in refused:  # both writers are retrying against the dead database
                    assert ev.wait(120)
                own_pg_cluster.start()
                stop.set()
                for t in ts:
                    t.join(180)
                assert not any(t.is_alive() for t in ts)
            assert seen and set(seen) == {(503, "1")}
            # the batches refused while it was down: retried with their keys
            for c, key in ((ca, "down-a"), (cb, "down-b")):
                book.ack(key, c.upload_rays(FIELD, *book.sent[key], idempotency_key=key))
        check_replicas(book, [a.url, b.url], probe)


def test_a_replica_on_an_empty_machine_needs_only_the_database_url(replicas, rng, pg_url):
    group = replicas()
    a = group.start()
    book = Book()
    probe = paper_rays(rng, 400)
    with Client(a.url, retries=0) as c:
        c.create_field(FIELD, channels=2, basis=ONE_CHART)
        book.uploads(c, rng, "s", 5, 2000)
        snap = c.snapshot(FIELD)  # into the database: chunked rows
        book.uploads(c, rng, "t", 3, 1000)
        before = c.query_rays(FIELD, *probe, weights=True)
    a.kill9()
    with psycopg.connect(pg_url) as db:
        (n, nbytes), = db.execute("SELECT count(*), sum(bytes) FROM flatserve.snapshots").fetchall()
    assert n == 1 and nbytes > 0
    fresh = group.start()  # nothing but the URL: a new, empty data directory
    assert not any((group.tmp / f"replica{group.n}").glob("snapshots/*"))
    with Client(fresh.url, retries=0) as c:
        info = c.describe(FIELD)
        assert info["storage"]["snapshot_batch"] == snap["batch"] == 5
        after = c.query_rays(FIELD, *probe, weights=True)
    np.testing.assert_array_equal(after.ids, before.ids)
    np.testing.assert_array_equal(after.values, before.values)
    check_replicas(book, [fresh.url], probe)


def test_kill9_of_the_replica_writing_a_snapshot(replicas, rng, pg_url):
    """Killed while it writes a snapshot into the database (at random moments of
    it): the others serve on, another replica writes the next snapshot at once
    (the lease died with the writer's connection: no 300 s lease to wait out),
    and no unreferenced snapshot data stays behind."""
    group = replicas(snapshot_lease_seconds=300)
    a, b = group.pair_with_field()
    book = Book()
    probe = paper_rays(rng, 400)
    with Client(a.url, retries=0) as c:
        book.uploads(c, rng, "s", 6, 4000)
    for rnd in range(3):
        with Client(a.url, retries=0, timeout=60) as c:
            t = threading.Thread(target=_quiet, args=(c.snapshot, FIELD))
            t.start()
            time.sleep(float(rng.uniform(0.05, 1.5)))
            a.kill9()
            t.join(60)
        with Client(b.url, retries=0) as c:
            book.upload(c, rng, f"after{rnd}", 500)
        with Client(b.url, retries=0) as c:
            snapshot_soon(c, name=FIELD)  # another replica writes the next one
        a = group.start()  # cleans up what the dead writer left (under the lease)
        with psycopg.connect(pg_url) as db:
            orphans = db.execute(
                "SELECT count(*) FROM flatserve.snapshots s WHERE NOT EXISTS (SELECT 1 FROM"
                " flatserve.fields f WHERE f.snapshot_file = s.name)").fetchone()[0]
            chunks = db.execute("SELECT count(*) FROM flatserve.snapshot_chunks c WHERE NOT EXISTS"
                                " (SELECT 1 FROM flatserve.snapshots s WHERE s.name = c.name)"
                                ).fetchone()[0]
        assert orphans == 0 and chunks == 0
        check_replicas(book, [a.url, b.url], probe)
    fresh = group.start()
    check_replicas(book, [fresh.url], probe)


def _quiet(fn, *args):
    try:
        fn(*args)
    except Exception:
        pass


def test_a_database_outage_during_the_restore_is_waited_out(tmp_path, own_pg_cluster, rng,
                                                             monkeypatch):
    """PostgreSQL unreachable while a replica restores (down when it starts; gone in
    the middle of a field's restore): the replica waits for it and then serves every
    stored field, instead of never becoming ready or holding the field as failed."""
    from fastapi.testclient import TestClient

    from flatserve.service import Settings, create_app
    from flatserve.service.rooms import applier as applier_mod

    url = own_pg_cluster.create_database("outage")

    def app():
        return create_app(Settings(data_dir=tmp_path / "data", database_url=url,
                                   snapshot_every=0))

    def restart_later(delay):
        t = threading.Timer(delay, own_pg_cluster.start)
        t.start()
        return t

    probe = paper_rays(rng, 300)
    with TestClient(base_url="http://127.0.0.1", app=app()) as tc:
        c = Client(http=tc)
        c.wait_ready(60)
        c.create_field(FIELD, channels=1, basis=ONE_CHART)
        for _ in range(3):
            c.upload_rays(FIELD, *paper_rays(rng, 300), rng.uniform(size=300))
        want = c.query_rays(FIELD, *probe)

    def check_serves(tc):
        c = Client(http=tc)
        c.wait_ready(90)
        assert c.describe(FIELD)["state"] == "ready"
        np.testing.assert_array_equal(c.query_rays(FIELD, *probe).values, want.values)

    own_pg_cluster.stop("immediate")  # down when the replica starts
    t = restart_later(1.0)
    with TestClient(base_url="http://127.0.0.1", app=app()) as tc:
        check_serves(tc)
    t.join()

    real = applier_mod.LogApplier._restore
    calls = []

    def restore(self, e, row, upto=None):  # the database goes in the middle of it
        if not calls:
            own_pg_cluster.stop("immediate")
            calls.append(restart_later(1.0))
        return real(self, e, row, upto)

    monkeypatch.setattr(applier_mod.LogApplier, "_restore", restore)
    with TestClient(base_url="http://127.0.0.1", app=app()) as tc:
        check_serves(tc)
    calls[0].join()
