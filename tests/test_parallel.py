"""flatserve.parallel: a field's shards on threads, answers bit for bit those of
the sequential loop whatever the number of threads."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from flatserve import Flats, parallel
from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.errors import InvalidInputError
from flatserve.grassmann import haar_frames
from flatserve.parallel import ShardPool, set_shard_threads, shard_pool


@pytest.fixture
def threads():
    """Set the process's shard threads for one test; the former pool back after."""
    before = shard_pool()
    yield set_shard_threads
    with parallel._pool_lock:
        parallel._pool = before


# -- the pool --------------------------------------------------------------------------
def test_map_keeps_the_order_of_the_work_whatever_finishes_first():
    rng = np.random.default_rng(1)
    delays = rng.uniform(0, 0.01, 40)
    pool = ShardPool(4)

    def work(i):
        time.sleep(delays[i])
        return i, threading.current_thread().name

    got = list(pool.map(work, range(40)))
    assert [i for i, _ in got] == list(range(40))
    assert len({name for _, name in got}) > 1  # it did run on several threads
    assert all(name.startswith("flatserve-shard") for _, name in got)
    pool.close()


def test_one_thread_one_item_or_inside_the_pool_runs_inline():
    here = threading.current_thread().name
    assert {n for n in ShardPool(1).map(lambda _: threading.current_thread().name, range(5))} \
        == {here}
    assert list(ShardPool(4).map(lambda _: threading.current_thread().name, [0])) == [here]
    pool = ShardPool(2)

    def outer(i):  # work started from a pool thread runs inline: it never waits for the pool
        me = threading.current_thread().name
        inner = list(pool.map(lambda _: threading.current_thread().name, range(6)))
        return me, set(inner)

    for me, inner in pool.map(outer, range(4)):
        assert inner == {me}
    pool.close()


def test_an_error_is_raised_in_its_place_after_the_running_items_finish():
    pool = ShardPool(2, window=2)
    started, finished = [], []
    lock = threading.Lock()

    def work(i):
        with lock:
            started.append(i)
        if i == 1:
            raise InvalidInputError("shard 1 failed", "x")
        time.sleep(0.05)
        with lock:
            finished.append(i)
        return i

    results = pool.map(work, range(10))
    assert next(results) == 0
    with pytest.raises(InvalidInputError, match="shard 1 failed"):
        next(results)
    # nothing runs on once the caller has its error: every item started has ended
    time.sleep(0.1)
    assert sorted(finished) == sorted(set(started) - {1})
    assert len(started) < 10  # the window: the rest never started
    pool.close()


def test_the_window_bounds_what_is_computed_ahead():
    pool = ShardPool(2, window=3)
    done = []
    results = pool.map(lambda i: done.append(i) or i, range(20))
    assert next(results) == 0
    time.sleep(0.05)
    assert len(done) <= 1 + 3  # the one read and at most the window ahead
    assert list(results) == list(range(1, 20))
    pool.close()


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_threads_must_be_a_whole_number_of_at_least_one(bad):
    with pytest.raises(InvalidInputError, match="threads: expected a whole number >= 1"):
        ShardPool(bad)


def test_default_threads_from_the_environment(monkeypatch):
    monkeypatch.setenv(parallel.THREADS_ENV, "3")
    assert parallel.default_threads() == 3
    monkeypatch.setenv(parallel.THREADS_ENV, "many")
    with pytest.raises(InvalidInputError, match=parallel.THREADS_ENV):
        parallel.default_threads()
    monkeypatch.delenv(parallel.THREADS_ENV)
    assert parallel.default_threads() >= 1


# -- fields on threads: the same bits ----------------------------------------------------
def _rays(rng, n, R=1.0):
    return Flats.from_rays(rng.uniform(-R, R, (n, 3)), rng.standard_normal((n, 3)))


def _build(kind: str, seed: int):
    """A field of ``kind`` filled with three batches (values of two channels)."""
    rng = np.random.default_rng(seed)
    if kind == "planes":
        field = AtlasField(Atlas.covering(2, 3), channels=2)
        batches = [Flats.from_parametric(haar_frames(1500, 3, 2, rng), rng.uniform(-1, 1, (1500, 3)))
                   for _ in range(3)]
    else:
        field = AtlasField(Atlas.covering(1, 3, oriented=kind == "rays"), channels=2)
        batches = [_rays(rng, 2000) for _ in range(3)]
    results = []
    for b in batches:
        vals = rng.uniform(size=(b.n, 2))
        results.append(field.insert_prepared(field.prepare(b, vals), slice_rows=700))
    return field, results


def _queries(kind, rng, n):
    if kind == "planes":
        return Flats.from_parametric(haar_frames(n, 3, 2, rng), rng.uniform(-2, 2, (n, 3)))
    return _rays(rng, n, 1.5)


@pytest.mark.parametrize("kind", ["lines", "rays", "planes"])
def test_answers_snapshots_and_restores_are_the_same_bits_on_any_number_of_threads(threads, kind):
    threads(1)
    want, want_adds = _build(kind, 5)
    q = _queries(kind, np.random.default_rng(6), 3000)
    want_q = want.query(q, return_weights=True)
    want_bytes = want.to_bytes()
    assert want.atlas.ncharts > 4 and want_q.inside.mean() > 0.3  # the check has a subject
    for n in (2, 3, 8):
        threads(n)
        got, got_adds = _build(kind, 5)
        for a, b in zip(got_adds, want_adds):
            assert (a.accepted, a.duplicates, a.nsamples) == (b.accepted, b.duplicates, b.nsamples)
            np.testing.assert_array_equal(a.rejected, b.rejected)
        assert got.samples_per_chart == want.samples_per_chart
        got_q = got.query(q, return_weights=True)
        for name in ("values", "inside", "status", "ids", "weights", "charts"):
            np.testing.assert_array_equal(np.asarray(getattr(got_q, name)),
                                          np.asarray(getattr(want_q, name)), err_msg=name)
        got_bytes = got.to_bytes()
        assert got_bytes == want_bytes  # the snapshot: byte for byte
        back = AtlasField.from_bytes(got_bytes)  # a restore on n threads
        assert back.to_bytes() == want_bytes
        again = back.query(q, return_weights=True)
        np.testing.assert_array_equal(again.values, want_q.values)
        np.testing.assert_array_equal(again.weights, want_q.weights)


def test_concurrent_queries_and_inserts_on_threads_match_the_sequential_field(threads):
    """Queries from several threads while batches go in (each query sees whole
    batches or whole slices, as on one thread); at the end, the same field."""
    threads(1)
    want, _ = _build("rays", 9)
    threads(2)
    field = AtlasField(Atlas.covering(1, 3, oriented=True), channels=2)
    rng = np.random.default_rng(9)
    batches = [_rays(rng, 2000) for _ in range(3)]
    values = [rng.uniform(size=(b.n, 2)) for b in batches]
    q = _queries("rays", np.random.default_rng(10), 500)
    stop, errors = threading.Event(), []

    def reader():
        try:
            while not stop.is_set():
                assert field.query(q).values.shape == (500, 2)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    readers = [threading.Thread(target=reader) for _ in range(3)]
    for t in readers:
        t.start()
    for b, v in zip(batches, values):
        field.insert_prepared(field.prepare(b, v), slice_rows=700)
    stop.set()
    for t in readers:
        t.join(30)
    assert not errors, errors
    assert field.to_bytes() == want.to_bytes()
