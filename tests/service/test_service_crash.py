"""Crash safety with a REAL server process: kill -9 at random moments (mid-upload
too), restart, and check that every acknowledged batch is there, that nothing is
stored twice or half, and that the restored field equals replaying exactly the
stored batches in-process; for the default (atlas) field and one chart at once."""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import numpy as np

from flatserve.client import Client
from tests.harness.process import ServerProcess, free_port  # noqa: F401

from .conftest import KINDS, add_rays, paper_rays, query_rays, upload_until_stopped

ROUNDS = 5
TIME_BUDGET_S = 150


Server = ServerProcess  # a real server process (kill -9 in the with block's exit)


def _verify(url, kind, sent, acked, probe):
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


def test_kill9_loses_nothing_acknowledged(tmp_path):
    rng = np.random.default_rng(7)
    data = tmp_path / "data"
    log = tmp_path / "server.log"
    sent = {str(kind): {} for kind in KINDS}
    acked = {str(kind): {} for kind in KINDS}
    probe = paper_rays(rng, 400)
    t_start = time.monotonic()
    rounds = 0
    try:
        for rnd in range(ROUNDS):
            if time.monotonic() - t_start > TIME_BUDGET_S and rnd >= 2:
                break
            with Server(data, log, snapshot_every=3000) as srv:
                srv.wait_ready()
                for kind in KINDS:
                    if rnd == 0:
                        with Client(srv.url) as c:
                            c.create_field(str(kind), channels=1, basis=kind.basis)
                    else:
                        _verify(srv.url, kind, sent[str(kind)], acked[str(kind)], probe)
                stop = threading.Event()
                ts = [threading.Thread(target=upload_until_stopped,
                                       args=(srv.url, str(kind), f"r{rnd}",
                                             np.random.default_rng([rnd, i]), sent[str(kind)],
                                             acked[str(kind)], stop),
                                       kwargs={"max_rows": 2500, "binary_every": 4})
                      for i, kind in enumerate(KINDS)]
                for t in ts:
                    t.start()
                time.sleep(float(rng.uniform(0.5, 2.5)))
                srv.kill9()
                stop.set()
                for t in ts:
                    t.join(timeout=60)
            rounds += 1
        with Server(data, log) as srv:
            srv.wait_ready()
            nstored = {str(kind): _verify(srv.url, kind, sent[str(kind)], acked[str(kind)],
                                          probe) for kind in KINDS}
    except BaseException:
        sys.stderr.write(log.read_text(errors="replace")[-5000:])
        raise
    text = log.read_text(errors="replace")
    print(f"\ncrash test: {rounds} kill -9 rounds; "
          f"{text.count('snapshot after batch') // 1} snapshot log lines, "
          f"{text.count('replaying')} restores")
    for name in sent:
        print(f"  {name}: {text.count(repr(name) + ': snapshot after batch')} snapshot lines")
    assert rounds >= 2
    for name in sent:
        inflight = len(sent[name]) - len(acked[name])
        deferred = sum(not a["indexed"] for a in acked[name].values())
        print(f"  {name}: {len(sent[name])} batches sent, {len(acked[name])} acknowledged "
              f"({deferred} with wait=false, before indexing), {nstored[name]} stored, "
              f"{inflight} in flight at a kill")
        assert acked[name] and nstored[name] >= len(acked[name]) and deferred


def test_flatserve_serve_command_binds_loopback_without_key(tmp_path):
    """`flatserve serve` starts the service; without an API key it refuses to listen
    beyond loopback (and says so), then shuts down cleanly on SIGTERM."""
    port = free_port()
    log = tmp_path / "serve.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "flatserve.cli", "serve", "--host", "0.0.0.0", "--port",
             str(port), "--data-dir", str(tmp_path / "d")],
            stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            with Client(f"http://127.0.0.1:{port}") as c:
                c.wait_ready(90)
                assert c.health() == {"status": "ok"}
                c.create_field("x")
        finally:
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=60)
    text = log.read_text()
    assert code in (0, -signal.SIGTERM), text  # uvicorn re-raises the signal it handled
    assert "Application shutdown complete" in text
    assert "no API key set: binding to 127.0.0.1 instead of 0.0.0.0" in text
    assert (tmp_path / "d" / "flatserve.sqlite3").exists()
