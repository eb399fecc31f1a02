"""The throwaway PostgreSQL cluster the backend's tests and benchmarks run on
(tests/harness/pgcluster.py): started on a free port, survives restarts and
crashes with committed data intact, and leaves nothing behind."""
from __future__ import annotations

import os
import subprocess

import psycopg
import pytest

from tests.harness.pgcluster import PgCluster, PgClusterError, process_alive


def test_cluster_commits_survive_restart_and_crash_and_close_removes_all():
    with PgCluster(fsync=True) as pg:
        url = pg.create_database("survive")
        with psycopg.connect(url, autocommit=True) as c:
            c.execute("CREATE TABLE t (i int PRIMARY KEY)")
            c.execute("INSERT INTO t SELECT generate_series(1, 100)")
            assert c.execute("SHOW fsync").fetchone() == ("on",)
            assert c.execute("SHOW listen_addresses").fetchone() == ("127.0.0.1",)
        port = pg.port
        pg.restart("fast")
        pg.restart("immediate")  # a crash: recovery from the WAL
        assert pg.port == port
        with psycopg.connect(url) as c:
            assert c.execute("SELECT count(*), sum(i) FROM t").fetchone() == (100, 5050)
        pid = pg.postmaster_pid()
        assert process_alive(pid)
        # the server runs as the postgres user when we are root
        owner = subprocess.run(["ps", "-o", "user=", "-p", str(pid)], capture_output=True,
                               text=True).stdout.strip()
        assert owner == ("postgres" if os.geteuid() == 0 else os.environ.get("USER", owner))
    assert not pg.dir.exists()
    assert not process_alive(pid)


def test_two_clusters_get_their_own_ports(pg_cluster):
    with PgCluster(fsync=False) as other:
        assert other.port != pg_cluster.port
        with psycopg.connect(other.url) as a, psycopg.connect(pg_cluster.url) as b:
            assert a.execute("SHOW port").fetchone()[0] == str(other.port)
            assert b.execute("SHOW port").fetchone()[0] == str(pg_cluster.port)


def test_database_names_are_checked(pg_cluster):
    with pytest.raises(ValueError):
        pg_cluster.create_database('x"; DROP DATABASE postgres; --')
    with pytest.raises(PgClusterError):
        pg_cluster.create_database("postgres")  # exists
