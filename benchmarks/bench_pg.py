"""The PostgreSQL backend against the SQLite one (issue 11 targets), on a
throwaway PostgreSQL cluster started here (fsync on: commits are real).

1. ``.npy`` ingest acknowledgement: time to the acknowledgement of a
   ``wait=false`` upload (batch validated, charted, committed: SQLite with
   ``synchronous=FULL`` in the data directory, or PostgreSQL over loopback),
   the same batches to one server of each kind, interleaved; the insert that
   follows is awaited, untimed, before the next run   -> ratio PostgreSQL / SQLite
2. replication lag on PostgreSQL: benchmarks/bench_replicas.py's measurement
   (a steady stream of 10k-ray uploads to replica A, acknowledgement on A to
   applied on B, p50 / p99, beside B's own chart + insert time) with both
   replicas on the cluster.
3. catch-up: a new replica on an empty machine (an empty data directory, the
   URL) restoring a ``--catchup-samples`` field from PostgreSQL (its snapshot,
   then the log after it), vs today's restart of one process on its own data
   directory (SQLite) with the same field    -> ratio

    PYTHONPATH=. python benchmarks/bench_pg.py [--rays 10000 50000] [--runs 7] [--only catchup]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time

import numpy as np

from bench_service import paper_rays
import timing  # noqa: F401  (first: the repository root on sys.path, for tests.harness)
from flatserve.client import Client
from tests.harness.pgcluster import PgCluster
from tests.harness.process import ServerProcess
from flatserve.service.server import limit_blas_threads


def ingest(args, pg: PgCluster) -> None:
    tmp = tempfile.mkdtemp(prefix="bench-pg-")
    rng = np.random.default_rng(1)
    try:
        url = pg.create_database("bench_ingest")
        with ServerProcess(os.path.join(tmp, "sqlite"), os.path.join(tmp, "sqlite.log"),
                           log_level="warning", snapshot_every=0, read_wait_timeout=600) as lite, \
                ServerProcess(os.path.join(tmp, "pg"), os.path.join(tmp, "pg.log"),
                              log_level="warning", snapshot_every=0, read_wait_timeout=600,
                              database_url=url) as pgs:
            lite.wait_ready()
            pgs.wait_ready()
            with Client(lite.url, timeout=600) as cl, Client(pgs.url, timeout=600) as cp:
                for c in (cl, cp):
                    c.create_field("ingest", channels=3, basis={"kind": "tangent_simplex"})
                for n in args.rays:
                    times = {"sqlite": [], "postgresql": []}
                    for run in range(args.runs):
                        o, d = paper_rays(rng, n)
                        v = rng.uniform(size=(n, 3))
                        order = [("sqlite", cl), ("postgresql", cp)]
                        if run % 2:
                            order.reverse()
                        for name, c in order:
                            t0 = time.perf_counter()
                            rep = c.upload_rays("ingest", o, d, v, wait=False)
                            times[name].append(time.perf_counter() - t0)
                            c.describe("ingest", min_position=rep["position"])  # untimed
                    s, p = statistics.median(times["sqlite"]), statistics.median(times["postgresql"])
                    print(f"1. .npy ingest acknowledgement, {n} rays (wait=false, medians of "
                          f"{args.runs}): SQLite {s * 1e3:.1f} ms | PostgreSQL {p * 1e3:.1f} ms | "
                          f"ratio {p / s:.2f}x")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def lag(args, pg: PgCluster) -> None:
    import bench_replicas

    url = pg.create_database("bench_lag")
    lag_args = argparse.Namespace(database_url=url, lag_rays=args.lag_rays, lag_base=args.lag_base,
                                  lag_batches=args.lag_batches, lag_period=args.lag_period)
    bench_replicas.replication_lag(lag_args, np.random.default_rng(2))
    print("   (both replicas on the PostgreSQL cluster: bench_replicas.py gives SQLite's)")


def _ready_at(start, probe, pos) -> float:
    """Seconds from starting a server process to its answer at log position ``pos``."""
    t0 = time.perf_counter()
    srv = start()
    srv.wait_ready(timeout=900, interval=0.02)
    with Client(srv.url, timeout=900) as c:
        c.query_rays("big", *probe, min_position=pos)
    dt = time.perf_counter() - t0
    srv.kill9()
    return dt


def catch_up(args, pg: PgCluster) -> None:
    """A new replica on an empty machine, from PostgreSQL alone, vs today's restart of
    a single process on its own data directory (SQLite), for the same field."""
    import bench_replicas

    n = args.catchup_samples
    tmp = tempfile.mkdtemp(prefix="bench-pg-")
    url = pg.create_database("bench_catchup")
    times = {}
    try:
        for kind, opts in (("sqlite", {}), ("postgresql", {"database_url": url})):
            rng = np.random.default_rng(3)
            data = os.path.join(tmp, kind)
            common = dict(log_level="warning", snapshot_every=0, read_wait_timeout=900, **opts)
            with ServerProcess(data, os.path.join(tmp, f"{kind}.log"), **common) as a:
                a.wait_ready(timeout=300)
                with Client(a.url, timeout=900) as c:
                    bench_replicas.fill(c, "big", n // 2, 10_000, rng)
                    c.snapshot("big")
                    for _ in range(n // 2 // 10_000):
                        o, d = paper_rays(rng, 10_000)
                        pos = c.upload_rays("big", o, d, rng.uniform(size=10_000))["position"]
            probe = paper_rays(rng, 10)
            runs = []
            for i in range(args.runs):  # SQLite: the same directory; PostgreSQL: an empty one
                where = data if kind == "sqlite" else os.path.join(tmp, f"empty{i}")
                runs.append(_ready_at(lambda: ServerProcess(
                    where, os.path.join(tmp, f"{kind}-{i}.log"), **common), probe, pos))
            times[kind] = statistics.median(runs)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s, p = times["sqlite"], times["postgresql"]
    print(f"3. catch-up of a {n}-sample field (snapshot after half, half in the log), start to "
          f"answering (medians of {args.runs}): single-process restart on its data directory "
          f"(SQLite) {s:.2f} s | new replica on an empty machine from PostgreSQL {p:.2f} s | "
          f"ratio {p / s:.2f}x")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--lag-rays", type=int, default=10_000)
    ap.add_argument("--lag-base", type=int, default=20_000)
    ap.add_argument("--lag-batches", type=int, default=20)
    ap.add_argument("--lag-period", type=float, default=1.0)
    ap.add_argument("--catchup-samples", type=int, default=100_000)
    ap.add_argument("--only", choices=("ingest", "lag", "catchup"), default=None)
    args = ap.parse_args(argv)
    limit_blas_threads(1)
    with PgCluster(fsync=True) as pg:
        print(f"PostgreSQL {pg.bindir.parent.name} (throwaway cluster, fsync on, loopback); "
              f"{os.cpu_count()} cores")
        if args.only in (None, "ingest"):
            ingest(args, pg)
        if args.only in (None, "lag"):
            lag(args, pg)
        if args.only in (None, "catchup"):
            catch_up(args, pg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
