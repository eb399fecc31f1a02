"""The data directory: one server at a time, and a full disk that costs no reads.

The full disk is real: a small tmpfs mounted for the test (the tests run as root,
as CI does), filled up with a file."""
from __future__ import annotations

import errno
import os
import subprocess
from contextlib import contextmanager

import numpy as np
import pytest

from flatserve.service.status import DataDirInUseError
from flatserve.service.log.storage import Storage
from tests.harness.fields import paper_rays
from tests.harness.process import ServerProcess
from tests.harness.service import assert_data_dir_refused, started


def test_second_storage_on_a_data_dir_in_use_is_refused(tmp_path):
    a = Storage(tmp_path / "data")
    with pytest.raises(DataDirInUseError) as ei:
        Storage(tmp_path / "data")
    assert str(tmp_path / "data") in str(ei.value) and str(os.getpid()) in str(ei.value)
    a.close()
    Storage(tmp_path / "data").close()  # free again once the first is closed


def test_second_server_on_a_data_dir_in_use_refuses_to_start(tmp_path):
    data = tmp_path / "data"
    with ServerProcess(data, tmp_path / "a.log") as srv:
        srv.wait_ready()
        assert_data_dir_refused(data, srv.proc.pid)
    # killed (the Server context kills -9): the directory is free again
    with ServerProcess(data, tmp_path / "b.log") as srv:
        srv.wait_ready()


@contextmanager
def small_disk(path, size="8m"):
    path.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                   check=True)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def fill(path) -> None:
    """Write a file until the file system is full (down to its last bytes)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        for size in (1 << 16, 4096, 512, 1):
            while True:
                try:
                    os.write(fd, b"\0" * size)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
                    break
    finally:
        os.close(fd)


def test_full_disk_refuses_writes_with_507_and_reads_go_on(tmp_path, make_app, rng):
    with small_disk(tmp_path / "disk") as disk:
        data = disk / "data"
        o, v = paper_rays(rng, 2000)
        probe = paper_rays(rng, 300)
        tc, c = started(make_app(data_dir=data))
        try:
            c.create_field("f", channels=1)
            c.upload_rays("f", o[:1000], v[:1000], np.ones(1000))
            want = c.query_rays("f", *probe)
            fill(disk / "filler")
            for wait in (True, False):
                r = tc.post("/v1/fields/f/samples", params={"wait": str(wait).lower()},
                            json={"origins": o[1000:].tolist(), "directions": v[1000:].tolist(),
                                  "values": np.ones((1000, 1)).tolist()})
                assert r.status_code == 507, r.text
                # nothing applied in memory, nothing to reload: reads go on at once
                info = c.describe("f")
                assert info["state"] == "ready" and info["storage"]["batches"] == 1
                got = c.query_rays("f", *probe)
                np.testing.assert_array_equal(got.values, want.values)
        finally:
            tc.__exit__(None, None, None)
        # a restart on the full disk serves reads and refuses writes
        tc, c = started(make_app(data_dir=data))
        try:
            np.testing.assert_array_equal(c.query_rays("f", *probe).values, want.values)
            r = tc.post("/v1/fields/f/samples",
                        json={"origins": o[1000:].tolist(), "directions": v[1000:].tolist(),
                              "values": np.ones((1000, 1)).tolist()})
            assert r.status_code == 507, r.text
            os.unlink(disk / "filler")  # space returns: writes work again
            rep = c.upload_rays("f", o[1000:], v[1000:], np.ones(1000))
            assert rep["batch"] == 2 and c.describe("f")["storage"]["batches"] == 2
        finally:
            tc.__exit__(None, None, None)


def test_postgresql_snapshot_staged_on_a_full_disk_is_507(tmp_path, make_app, rng, pg_url):
    """The PostgreSQL backend stages a snapshot in the data directory: a full disk
    there is a 507, as with the SQLite backend (not a 503, never a 500); the field
    and its stored batches are untouched."""
    with small_disk(tmp_path / "disk") as disk:
        data = disk / "data"
        data.mkdir()
        tc, c = started(make_app(data_dir=data, database_url=pg_url))
        try:
            c.create_field("f", channels=1)
            c.upload_rays("f", *paper_rays(rng, 1000), np.ones(1000))
            fill(disk / "filler")
            r = tc.post("/v1/fields/f/snapshot")
            assert r.status_code == 507, r.text
            os.unlink(disk / "filler")
            assert c.snapshot("f")["batch"] == 1
            assert c.describe("f")["storage"]["batches"] == 1
        finally:
            tc.__exit__(None, None, None)
