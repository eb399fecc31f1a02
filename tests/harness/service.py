"""Helpers of the service tests: an app started in-process, uploads that go on
while servers are killed and the check of what they stored afterwards, snapshots
retried while another writer holds the lease, a second server refused a data dir."""
from __future__ import annotations

import subprocess
import sys
import time
from contextlib import contextmanager

import numpy as np
from fastapi.testclient import TestClient

from flatserve.client import Client, ServiceError

from .fields import add_rays, paper_rays, query_rays


def upload_until_stopped(url, field, tag, rng, sent, acked, stop, *, max_rows, binary_every,
                         survive=False):
    """Upload random batches of paper rays to ``field`` until ``stop`` is set.

    Each batch's rays go into ``sent[key]`` before it is sent and its answer into
    ``acked[key]`` once acknowledged (``key`` is ``f"{tag}-b{i}"``, also the
    Idempotency-Key); every other batch is acknowledged before it is indexed
    (wait=false), one in ``binary_every`` goes as JSON. When the server dies under
    it, the uploader returns, or with ``survive`` pauses and goes on (a sibling
    replica behind the same URL).
    """
    c = Client(url, retries=0, timeout=30)
    i = 0
    try:
        while not stop.is_set():
            n = int(rng.integers(20, max_rows))
            o, v = paper_rays(rng, n)
            val = rng.uniform(size=(n, 1))
            key = f"{tag}-b{i}"
            sent[key] = (o, v, val)
            try:
                acked[key] = c.upload_rays(field, o, v, val, idempotency_key=key,
                                           binary=bool(i % binary_every), wait=bool(i % 2))
            except Exception:
                if stop.is_set() or not survive:
                    return
                time.sleep(0.05)
            i += 1
    finally:
        c.close()


def verify_stored(url, kind, sent, acked, probe) -> int:
    """Check the field ``kind`` of the server at ``url`` after uploads (and kill -9s) by
    :func:`upload_until_stopped`: every acknowledged batch stored, none twice or half,
    its answers those of replaying exactly the stored batches into the library field,
    and a retry of an acknowledged batch replayed, not stored again. The number of
    batches stored."""
    name = str(kind)
    with Client(url, retries=0) as c:
        stored = c.batches(name)
        keys = [b["idempotency_key"] for b in stored]
        assert len(keys) == len(set(keys)), "a batch was stored twice"
        assert [b["batch"] for b in stored] == sorted(b["batch"] for b in stored)
        missing = set(acked) - set(keys)
        assert not missing, f"acknowledged batches lost: {sorted(missing)}"
        ref = kind.reference(1)
        for b in stored:
            o, v, val = sent[b["idempotency_key"]]
            assert b["rows"] == len(o), "a batch was stored half"
            res = add_rays(ref, o, v, val)
            assert b["accepted"] == res.accepted
            if b["idempotency_key"] in acked:
                assert acked[b["idempotency_key"]]["accepted"] == res.accepted
        info = c.describe(name, verbose=True)
        assert info["nsamples"] == ref.nsamples
        if kind.atlas:  # every chart restored: the same samples per chart
            assert [ch["samples"] for ch in info["charts"]] == ref.samples_per_chart
            assert info["nvertices"] == ref.nstored and info["nsimplex"] == ref.nsimplex
        got = c.query_rays(name, *probe, weights=not kind.atlas)
        want = query_rays(ref, *probe, return_weights=not kind.atlas)
        np.testing.assert_array_equal(got.inside, want.inside)
        if not kind.atlas:  # (an atlas field returns no simplices)
            np.testing.assert_array_equal(got.ids, want.ids)
        np.testing.assert_allclose(got.values, want.values, atol=1e-12, equal_nan=True)
        # a retry of an acknowledged batch is recognised, not stored again
        if acked:
            key = sorted(acked)[0]
            again = c.upload_rays(name, *sent[key], idempotency_key=key)
            assert again["replayed"]
            assert len(c.batches(name)) == len(stored)
        return len(stored)


def snapshot_soon(c: Client, patience: float = 30.0, *, name: str,
                  interval: float = 0.05) -> dict:
    """A snapshot of ``name`` through ``c``; 503 ("another replica is writing a
    snapshot", or in cluster mode a shard catching up with the front's position) is
    retried every ``interval`` seconds (here while PostgreSQL ends the killed
    writer's session: milliseconds; the patience is far below the 300 s lease a row
    alone would need)."""
    end = time.monotonic() + patience
    while True:
        try:
            return c.snapshot(name)
        except ServiceError as exc:
            if exc.status != 503 or time.monotonic() > end:
                raise
            time.sleep(interval)


def save_bytes(data: bytes):
    """A snapshot writer for ``LogBackend.write_snapshot`` (``save(path, stage)``)
    that writes ``data`` and names no parts."""
    def save(path, stage):
        with open(path, "wb") as fh:
            fh.write(data)
    return save


def assert_data_dir_refused(data, holder_pid):
    """A second server started on ``data`` exits with 2, naming the holder's pid."""
    out = subprocess.run([sys.executable, "-m", "flatserve.service", "--port", "1",
                          "--data-dir", str(data)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "in use by another flatserve server" in out.stderr, out.stderr
    assert f"pid {holder_pid}" in out.stderr


@contextmanager
def running(app):
    """``(TestClient, Client)`` of ``app`` started and ready (:func:`started`), its
    lifespan exited at the end of the block."""
    tc, c = started(app)
    try:
        yield tc, c
    finally:
        tc.__exit__(None, None, None)


def started(app):
    """Enter ``app``'s lifespan (the caller exits it) and wait until it is ready."""
    tc = TestClient(base_url="http://127.0.0.1", app=app)
    tc.__enter__()
    c = Client(http=tc)
    c.wait_ready(60)
    return tc, c
