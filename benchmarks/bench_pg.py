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

    PYTHONPATH=. python benchmarks/bench_pg.py [--rays 10000 50000] [--runs 7]
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
from flatserve.client import Client
from flatserve.service.pgcluster import PgCluster
from flatserve.service.process import ServerProcess
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
                    c.create_field("ingest", channels=3)
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--lag-rays", type=int, default=10_000)
    ap.add_argument("--lag-base", type=int, default=20_000)
    ap.add_argument("--lag-batches", type=int, default=20)
    ap.add_argument("--lag-period", type=float, default=1.0)
    ap.add_argument("--only", choices=("ingest", "lag"), default=None)
    args = ap.parse_args(argv)
    limit_blas_threads(1)
    with PgCluster(fsync=True) as pg:
        print(f"PostgreSQL {pg.bindir.parent.name} (throwaway cluster, fsync on, loopback); "
              f"{os.cpu_count()} cores")
        if args.only in (None, "ingest"):
            ingest(args, pg)
        if args.only in (None, "lag"):
            lag(args, pg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
