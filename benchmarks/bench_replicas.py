"""Replicas on one shared log (issue 11 targets).

1. small queries (1-8 rays, wrk, ``--clients`` keep-alive connections) against
   ``serve --processes 2`` vs ``--processes 1`` on the same field
                                   -> queries/s, ratio (target >= 1.5x on 2 cores);
   the load generator's CPU share of the machine is printed beside each figure
   (it runs on the same cores as the servers).
2. replication lag under a steady stream of ``--lag-rays``-ray ``.npy`` uploads
   (``wait=false``) to replica A: from A's acknowledgement to replica B having
   applied the batch (a 1-ray query on B with ``min_position`` = the upload's
   position, minus that query's own time measured on a caught-up replica)
                                   -> p50 / p99, next to the time B needs to
                                      chart + insert such a batch in-process
                                      (target p99 <= that + 100 ms).
3. catch-up of a replica for a ``--catchup-samples``-sample field (a snapshot
   covering half the batches, the rest in the log): a new replica joining while
   A runs, vs today's single-process restart on the same data directory (time
   from the process start to ``/readyz`` 200 and the field answering).

Backend: SQLite in a temporary data directory (default), or ``--database-url
postgresql://...`` (the replicas then share that database; no data-dir lock).

    PYTHONPATH=. python benchmarks/bench_replicas.py [--seconds 5] [--clients 8]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import tempfile
import time

import numpy as np
import orjson

from bench_service import paper_rays, small_queries_wrk
import timing  # noqa: F401  (first: the repository root on sys.path, for tests.harness)
from flatserve.client import Client
from flatserve.field import Field
from flatserve.service.rooms import specs
from tests.harness.process import ServerProcess
from flatserve.service.server import limit_blas_threads


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


class Group:
    """Replica processes on one backend (SQLite: one data dir and its lock)."""

    def __init__(self, tmp, database_url=None, **options):
        self.tmp, self.url, self.options = tmp, database_url, options
        self.data = os.path.join(tmp, "data")
        self.fd = None
        if database_url is None:
            from flatserve.service.log.storage import lock_data_dir

            self.fd = lock_data_dir(self.data)
        self.procs = []

    def start(self, name, **kw):
        opts = dict(self.options, **kw)
        if self.url:
            opts["database_url"] = self.url
        else:
            opts["lock_fd"] = self.fd
        p = ServerProcess(self.data, os.path.join(self.tmp, f"{name}.log"), log_level="warning",
                          **opts)
        self.procs.append(p)
        return p

    def close(self):
        for p in self.procs:
            p.kill9()
        if self.fd is not None:
            os.close(self.fd)


def fill(c, name, n, batch, rng, channels=1):
    # the paper's single chart (its rays all lie in it): figures comparable with the
    # README's earlier ones, and a 1M-sample field within the default max_simplices
    c.create_field(name, channels=channels, basis={"kind": "tangent_simplex"})
    pos = 0
    for lo in range(0, n, batch):
        m = min(batch, n - lo)
        o, v = paper_rays(rng, m)
        pos = c.upload_rays(name, o, v, rng.uniform(size=(m, channels)))["position"]
    return pos


# -- 1. small queries ------------------------------------------------------------------------
def small_queries(args, rng):
    import shutil as _sh

    wrk = _sh.which("wrk")
    if wrk is None:
        print("1. small queries: wrk not found (apt-get install wrk); skipped")
        return
    small = [paper_rays(np.random.default_rng(i), int(1 + i % 8)) for i in range(64)]
    bodies = [orjson.dumps({"origins": o, "directions": v}, option=orjson.OPT_SERIALIZE_NUMPY)
              for o, v in small]
    out = {}
    for procs in (1, 2):
        tmp = tempfile.mkdtemp(prefix="bench-replicas-")
        try:
            opts = dict(snapshot_every=0, processes=procs)
            if args.database_url:
                opts["database_url"] = args.database_url
            with ServerProcess(os.path.join(tmp, "data"), os.path.join(tmp, "s.log"),
                               log_level="warning", **opts) as srv:
                srv.wait_ready()
                with Client(srv.url, timeout=300) as c:
                    fill(c, "bench", args.samples, 20_000, rng)
                time.sleep(1.0)  # every replica caught up (min_position is not used by wrk)
                cpu0, t0 = _children_cpu(), time.perf_counter()
                rate, p50, p99 = small_queries_wrk(wrk, srv.url, "", bodies, args)
                wall = time.perf_counter() - t0
                share = (_children_cpu() - cpu0) / (wall * os.cpu_count())
                out[procs] = rate
                print(f"1. small queries, --processes {procs}: {rate:8.0f} queries/s, p50 "
                      f"{p50:.2f} ms, p99 {p99:.2f} ms (wrk -c{args.clients}; wrk used "
                      f"{share:.0%} of the {os.cpu_count()} cores)")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"   --processes 2 vs 1: ratio {out[2] / out[1]:.2f}x (target >= 1.5x)")


# -- 2. replication lag ------------------------------------------------------------------------
def replication_lag(args, rng):
    n = args.lag_rays
    # the peer: the time replica B needs to apply one batch (chart + insert), in-process,
    # into a field of the size B's reaches halfway through the stream
    fld = Field(specs.build_basis(None, 1, 3), channels=1)
    o, v = paper_rays(rng, args.lag_base)
    fld.add_rays(o, v, rng.uniform(size=args.lag_base))
    apply_s = []
    for _ in range(args.lag_batches // 2):
        o, v = paper_rays(rng, n)
        val = rng.uniform(size=n)
        t0 = time.perf_counter()
        fld.insert_prepared(fld.prepare(_flats(o, v), val), slice_rows=20_000)
        apply_s.append(time.perf_counter() - t0)
    peer = statistics.median(apply_s)
    tmp = tempfile.mkdtemp(prefix="bench-replicas-")
    g = Group(tmp, args.database_url, snapshot_every=0, read_wait_timeout=120)
    try:
        a, b = g.start("a"), g.start("b")
        a.wait_ready()
        b.wait_ready()
        probe = paper_rays(rng, 1)
        with Client(a.url, timeout=300) as ca, Client(b.url, timeout=300) as cb:
            pos = fill(ca, "lag", args.lag_base, 20_000, rng)
            cb.query_rays("lag", *probe, min_position=pos)
            qs = []
            for _ in range(20):  # a 1-ray query on a caught-up replica
                t0 = time.perf_counter()
                cb.query_rays("lag", *probe, min_position=pos)
                qs.append(time.perf_counter() - t0)
            q = statistics.median(qs)
            lags, applies = [], []
            period = max(args.lag_period, 2.0 * peer)
            for _ in range(args.lag_batches):
                o, v = paper_rays(rng, n)
                val = rng.uniform(size=n)
                s0, n0 = _apply_stats(cb)
                t_start = time.perf_counter()
                rep = ca.upload_rays("lag", o, v, val, wait=False)
                t_ack = time.perf_counter()
                cb.query_rays("lag", *probe, min_position=rep["position"])
                lags.append(max(0.0, time.perf_counter() - t_ack - q))
                s1, n1 = _apply_stats(cb)
                assert n1 - n0 == 1
                applies.append(s1 - s0)  # B's own chart + insert of this batch
                time.sleep(max(0.0, period - (time.perf_counter() - t_start)))
    finally:
        g.close()
        shutil.rmtree(tmp, ignore_errors=True)
    lags, applies = np.array(lags), np.array(applies)
    p50, p99 = np.percentile(lags, 50), np.percentile(lags, 99)
    over = lags - applies
    print(f"2. replication lag, {n}-ray .npy uploads (wait=false) every {period:.2f} s "
          f"({len(lags)} batches, field of {args.lag_base}+ samples): ack on A -> applied on B "
          f"p50 {p50 * 1e3:.0f} ms, p99 {p99 * 1e3:.0f} ms | B's chart+insert of each batch "
          f"(flatserve_log_apply_seconds, same run) p50 {np.median(applies) * 1e3:.0f} ms, "
          f"p99 {np.percentile(applies, 99) * 1e3:.0f} ms; in-process alone "
          f"{peer * 1e3:.0f} ms\n   lag - B's insert of the same batch: p50 "
          f"{np.median(over) * 1e3:.0f} ms, p99 {np.percentile(over, 99) * 1e3:.0f} ms "
          f"(target p99 <= 100 ms)")


def _apply_stats(c):
    """(sum, count) of ``flatserve_log_apply_seconds`` of a replica."""
    text = c.metrics()
    get = lambda k: float(next(ln.split()[-1] for ln in text.splitlines()  # noqa: E731
                               if ln.split("{")[0].split()[0:1] == [f"flatserve_log_apply_seconds_{k}"]))
    return get("sum"), get("count")


def _flats(o, v):
    from flatserve.flats import Flats

    return Flats.from_rays(o, v)


# -- 3. catch-up ---------------------------------------------------------------------------------
def _time_to_ready(start, name, probe, pos):
    """Seconds from starting a replica process to its answer at log position ``pos``."""
    t0 = time.perf_counter()
    srv = start()
    srv.wait_ready(timeout=900, interval=0.02)
    with Client(srv.url, timeout=300) as c:
        c.query_rays(name, *probe, min_position=pos)
    dt = time.perf_counter() - t0
    srv.kill9()
    return dt


def catch_up(args, rng):
    n = args.catchup_samples
    tmp = tempfile.mkdtemp(prefix="bench-replicas-")
    g = Group(tmp, args.database_url, snapshot_every=0, read_wait_timeout=600)
    try:
        a = g.start("a")
        a.wait_ready(timeout=300)
        probe = paper_rays(rng, 10)
        with Client(a.url, timeout=900) as ca:
            half = fill(ca, "big", n // 2, 10_000, rng)
            ca.snapshot("big")
            for _ in range(n // 2 // 10_000):
                o, v = paper_rays(rng, 10_000)
                pos = ca.upload_rays("big", o, v, rng.uniform(size=10_000))["position"]
        del half
        # interleaved: a new replica joins while A runs; then A is stopped and one
        # process restarts alone (today's restart); A is started again, untimed
        joins, restarts = [], []
        for i in range(args.runs):
            joins.append(_time_to_ready(lambda: g.start(f"b{i}"), "big", probe, pos))
            a.kill9()
            restarts.append(_time_to_ready(lambda: g.start(f"r{i}"), "big", probe, pos))
            a = g.start(f"a{i}")
            a.wait_ready(timeout=900)
    finally:
        g.close()
        shutil.rmtree(tmp, ignore_errors=True)
    j, r = statistics.median(joins), statistics.median(restarts)
    print(f"3. catch-up, {n}-sample field (snapshot after half, half in the log): new replica "
          f"joining a running one {j:.2f} s | single-process restart {r:.2f} s | ratio "
          f"{j / r:.2f}x")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--database-url", default=None, help="postgresql://... (default SQLite)")
    ap.add_argument("--samples", type=int, default=20_000, help="field size for 1.")
    ap.add_argument("--seconds", type=float, default=5.0, help="wrk run length (3 runs)")
    ap.add_argument("--clients", type=int, default=8, help="wrk connections")
    ap.add_argument("--lag-rays", type=int, default=10_000)
    ap.add_argument("--lag-base", type=int, default=20_000)
    ap.add_argument("--lag-batches", type=int, default=20)
    ap.add_argument("--lag-period", type=float, default=1.0, help="seconds between uploads "
                    "(at least twice B's insert time)")
    ap.add_argument("--catchup-samples", type=int, default=100_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--only", choices=("queries", "lag", "catchup"), default=None)
    args = ap.parse_args(argv)
    limit_blas_threads(1)
    rng = np.random.default_rng(0)
    print(f"backend: {'PostgreSQL ' + args.database_url.split('@')[-1] if args.database_url else 'SQLite'}; "
          f"{os.cpu_count()} cores")
    if args.only in (None, "queries"):
        small_queries(args, rng)
    if args.only in (None, "lag"):
        replication_lag(args, rng)
    if args.only in (None, "catchup"):
        catch_up(args, rng)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
