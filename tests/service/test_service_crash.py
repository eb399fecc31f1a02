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
from tests.harness.fields import KINDS, paper_rays
from tests.harness.process import ServerProcess, free_port
from tests.harness.service import upload_until_stopped, verify_stored

ROUNDS = 5
TIME_BUDGET_S = 150


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
            with ServerProcess(data, log, snapshot_every=3000) as srv:
                srv.wait_ready()
                for kind in KINDS:
                    if rnd == 0:
                        with Client(srv.url) as c:
                            c.create_field(str(kind), channels=1, basis=kind.basis)
                    else:
                        verify_stored(srv.url, kind, sent[str(kind)], acked[str(kind)], probe)
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
        with ServerProcess(data, log) as srv:
            srv.wait_ready()
            nstored = {str(kind): verify_stored(srv.url, kind, sent[str(kind)],
                                                acked[str(kind)], probe) for kind in KINDS}
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
