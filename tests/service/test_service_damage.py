"""Damaged files and exhausted file descriptors, with REAL server processes: a
damaged or truncated database stops the server at start with one clear line naming
the file (no traceback); a damaged snapshot is replaced by replaying the batches,
and the log says so; a server out of file descriptors keeps running, keeps serving
the connections it holds, and recovers once the connections close."""
from __future__ import annotations

import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from flatserve.client import Client
from tests.harness.fields import paper_rays
from tests.harness.process import ServerProcess, free_port

DB = "flatserve.sqlite3"


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A data dir holding one field of 12 batches and a snapshot after batch 12, and
    the answers of a probe query."""
    d = tmp_path_factory.mktemp("stored")
    rng = np.random.default_rng(5)
    probe = paper_rays(rng, 300)
    with ServerProcess(d / "data", d / "server.log") as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            c.create_field("f", channels=1)
            for i in range(12):
                o, v = paper_rays(rng, 400)
                c.upload_rays("f", o, v, rng.uniform(size=(400, 1)), binary=bool(i % 2),
                              idempotency_key=f"k{i}")
            c.snapshot("f")
            answers = c.query_rays("f", *probe)
            batches = c.batches("f")
        srv.proc.send_signal(signal.SIGTERM)  # a clean stop: everything in the main file
        assert srv.proc.wait(60) in (0, -signal.SIGTERM)
    assert not (d / "data" / (DB + "-wal")).exists()
    return d / "data", probe, answers, batches


def _copy(src, dst):
    shutil.copytree(src, dst)
    os.remove(dst / "flatserve.lock")
    return dst


def _start_expecting_refusal(data, log):
    port = free_port()
    with open(log, "wb") as fh:
        proc = subprocess.run(
            [sys.executable, "-m", "flatserve.service", "--port", str(port), "--data-dir",
             str(data)], stdout=fh, stderr=subprocess.STDOUT, timeout=60)
    return proc.returncode, log.read_text()


def _damage_truncated(path):
    os.truncate(path, os.path.getsize(path) // 2)


def _damage_header(path):
    with open(path, "r+b") as fh:
        fh.write(np.random.default_rng(1).bytes(100))


def _damage_pages(path):
    size = os.path.getsize(path)
    assert size >= 8 * 65536  # pages of 64 KiB: overwrite three in the middle
    with open(path, "r+b") as fh:
        fh.seek(3 * 65536)
        fh.write(np.random.default_rng(2).bytes(3 * 65536))


@pytest.mark.parametrize("damage", [_damage_truncated, _damage_header, _damage_pages],
                         ids=["truncated", "header", "pages"])
def test_damaged_database_is_refused_naming_the_file(stored, tmp_path, damage):
    data = _copy(stored[0], tmp_path / "data")
    damage(data / DB)
    code, text = _start_expecting_refusal(data, tmp_path / "server.log")
    assert code == 2, text
    assert "Traceback" not in text, text
    line = [ln for ln in text.splitlines() if " ERROR " in ln]
    assert len(line) == 1, text
    assert str(data / DB) in line[0]
    assert "damaged" in line[0] and "backup" in line[0], line[0]
    assert "Uvicorn running" not in text  # nothing was served


def test_intact_copy_starts(stored, tmp_path):
    """The refusals above come from the damage, not from the copying."""
    data, probe, answers, batches = stored
    data = _copy(data, tmp_path / "data")
    with ServerProcess(data, tmp_path / "server.log") as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            assert c.batches("f") == batches
            np.testing.assert_array_equal(c.query_rays("f", *probe).values, answers.values)


def test_damaged_snapshot_is_replaced_by_the_batches(stored, tmp_path):
    data, probe, answers, batches = stored
    data = _copy(data, tmp_path / "data")
    snaps = list((data / "snapshots").glob("*.snap"))
    assert len(snaps) == 1
    raw = bytearray(snaps[0].read_bytes())
    raw[len(raw) // 2:len(raw) // 2 + 64] = bytes(64)  # damage inside: checksums catch it
    snaps[0].write_bytes(bytes(raw))
    log = tmp_path / "server.log"
    with ServerProcess(data, log) as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            assert c.describe("f")["state"] == "ready"
            assert c.batches("f") == batches
            got = c.query_rays("f", *probe)
            np.testing.assert_array_equal(got.values, answers.values)
    text = log.read_text()
    assert f"field 'f': snapshot {snaps[0]} unusable" in text
    assert "rebuilding from batches" in text
    assert "field 'f': replaying 12 of 12 stored batch(es)" in text


def _limit_fds():
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))


def test_file_descriptor_exhaustion_recovers(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log = tmp_path / "server.log"
    rng = np.random.default_rng(3)
    with open(log, "wb") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "flatserve.service", "--port", str(port), "--data-dir",
             str(tmp_path / "data"), "--header-timeout", "60"],
            stdout=fh, stderr=subprocess.STDOUT, start_new_session=True, preexec_fn=_limit_fds)
    socks = []
    try:
        held = Client(url, retries=0, timeout=30)  # a keep-alive connection opened first
        held.wait_ready(60)
        held.create_field("f", channels=1)
        o, v = paper_rays(rng, 500)
        n1 = held.upload_rays("f", o, v, np.ones((500, 1)))["accepted"]
        for _ in range(150):  # far more connections than descriptors
            s = socket.socket()
            s.settimeout(5)
            try:
                s.connect(("127.0.0.1", port))
            except OSError:
                s.close()
                break
            socks.append(s)
        time.sleep(1.0)
        assert proc.poll() is None
        assert len(os.listdir(f"/proc/{proc.pid}/fd")) >= 40  # the limit was approached
        # the connection it holds keeps being served
        for _ in range(3):
            assert held.describe("f")["nsamples"] == n1
            assert np.isfinite(held.query_rays("f", o[:50], v[:50]).values).all()
        for s in socks:
            s.close()
        socks = []
        deadline = time.monotonic() + 15
        while True:  # new connections are served again
            try:
                r = httpx.get(url + "/healthz", timeout=2)
                if r.status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the server did not recover"
            time.sleep(0.2)
        with Client(url, retries=0, timeout=30) as c:
            o2, v2 = paper_rays(rng, 500)
            n2 = c.upload_rays("f", o2, v2, np.ones((500, 1)))["accepted"]
            assert c.snapshot("f")["batch"] == 2
            assert c.describe("f")["nsamples"] == n1 + n2 > 900
        held.close()
        assert proc.poll() is None
    finally:
        for s in socks:
            s.close()
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)
    text = log.read_text()
    assert "max_connections 1000 lowered to 32: the open-files limit is 64" in text, text
    assert "Traceback" not in text, text[-3000:]


@pytest.mark.parametrize("limits, requested, want", [
    ((64, 64), 1000, "32 max_connections 1000 lowered to 32: the open-files limit is 64"),
    ((256, 4096), 1000, "1000 open-files limit raised from 256 to 1064"),
    ((256, 512), 1000, "448 open-files limit raised from 256 to 512; max_connections 1000 "
                       "lowered to 448"),
    ((4096, 4096), 100, "100 None"),
    ((4096, 4096), 0, "4032 None"),
])
def test_connection_cap_fits_the_open_files_limit(limits, requested, want):
    code = ("from flatserve.service.http.connections import connection_cap\n"
            f"cap, note = connection_cap({requested})\nprint(cap, note)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, limits),
                         timeout=60, check=True).stdout
    assert out.startswith(want), out
