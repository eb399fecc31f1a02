"""Service vs in-process Field on the same data (issue 4 targets).

1. 250,000-ray query: binary (.npy) round trip over loopback vs the in-process
   ``Field.query_rays`` call            -> ratio, target <= 1.3x
2. upload of one batch: binary (.npy) vs the same batch as JSON
                                        -> ratio, target >= 5x (also printed:
   the in-process insert time, i.e. what no transport can remove)
3. small queries (1-8 rays) from a concurrent client (threads, keep-alive)
                                        -> queries/s (target >= 1000), p50/p99

A real server process (``python -m flatserve.service``) on a free loopback port
with a temporary data dir. Medians of several runs.

    .venv/bin/python benchmarks/bench_service.py [--samples 20000] [--queries 250000]
"""
from __future__ import annotations

import argparse
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from flatserve.client import Client, server_timing
from flatserve.field import Field
from flatserve.service import specs


def paper_rays(rng, n):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def timed(fn, runs):
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def interleaved(peer, ours, runs):
    a, b = [], []
    for _ in range(runs):
        t0 = time.perf_counter()
        peer()
        t1 = time.perf_counter()
        ours()
        a.append(t1 - t0)
        b.append(time.perf_counter() - t1)
    return statistics.median(a), statistics.median(b)


def _small_client(url, seconds, threads, q):
    """One client process: ``threads`` keep-alive clients querying 1-8 rays each."""
    small = [paper_rays(np.random.default_rng(i), int(1 + i % 8)) for i in range(256)]
    lat, stop = [], threading.Event()

    def worker(k):
        with Client(url) as cl:
            i = k * 31
            while not stop.is_set():
                so, sv = small[i % len(small)]
                t0 = time.perf_counter()
                cl.query_rays("bench", so, sv)
                lat.append(time.perf_counter() - t0)
                i += 1

    ts = [threading.Thread(target=worker, args=(k,)) for k in range(threads)]
    for t in ts:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in ts:
        t.join()
    q.put(lat)


def line(what, peer_name, peer, ours_name, ours, ratio, target):
    print(f"{what:<34} {peer_name} {peer:>9.4f} s | {ours_name} {ours:>9.4f} s | "
          f"ratio {ratio:6.2f}x (target {target})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20_000, help="samples in the field")
    ap.add_argument("--queries", type=int, default=250_000, help="rays in the big query")
    ap.add_argument("--upload", type=int, default=50_000, help="rays in the upload batch")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=4.0, help="duration of the small-query test")
    ap.add_argument("--clients", type=int, default=8, help="concurrent small-query clients")
    ap.add_argument("--procs", type=int, default=2, help="client processes sharing them")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    C = 3

    tmp = tempfile.TemporaryDirectory(prefix="flatserve-bench-")
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "flatserve.service", "--port", str(port), "--data-dir", tmp.name,
         "--log-level", "warning", "--snapshot-every", "0"], start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        c = Client(url, timeout=600)
        c.wait_ready(120)
        o, v = paper_rays(rng, args.samples)
        val = rng.uniform(size=(args.samples, C))
        ref = Field(specs.build_basis(None, 1, 3), channels=C)
        ref.add_rays(o, v, val)
        c.create_field("bench", channels=C)
        c.upload_rays("bench", o, v, val)
        assert c.describe("bench")["nsamples"] == ref.nsamples
        print(f"field: {ref.nsamples} samples (k=1, d=3, {C} channels), "
              f"server and in-process built from the same rays")

        # 1. big query -------------------------------------------------------
        qo, qv = paper_rays(rng, args.queries)
        want = ref.query_rays(qo, qv)
        got = c.query_rays("bench", qo, qv)
        assert np.array_equal(got.inside, want.inside)
        assert np.allclose(got.values, want.values, equal_nan=True)
        # interleaved (in-process, HTTP) pairs: load from other processes hits both alike
        t_in, t_http = interleaved(lambda: ref.query_rays(qo, qv),
                                   lambda: c.query_rays("bench", qo, qv), args.runs)
        line(f"query {args.queries} rays", "in-process", t_in, "HTTP .npy", t_http,
             t_http / t_in, "<= 1.3x")

        # 2. upload ------------------------------------------------------------
        uo, uv = paper_rays(rng, args.upload)
        uval = rng.uniform(size=(args.upload, C))
        runs = max(2, args.runs // 2)
        counter = iter(range(10**6))

        def fresh():
            name = f"up{next(counter)}"
            c.create_field(name, channels=C)
            return name

        inserts = {True: [], False: []}

        def up(binary):
            name = fresh()
            t0 = time.perf_counter()
            c.upload_rays(name, uo, uv, uval, binary=binary)
            dt = time.perf_counter() - t0
            inserts[binary].append(server_timing(c.last_response)["insert"])
            c.delete_field(name)
            return dt

        def add_in_process():
            t0 = time.perf_counter()
            Field(specs.build_basis(None, 1, 3), channels=C).add_rays(uo, uv, uval)
            return time.perf_counter() - t0

        tb, tj, ta = [], [], []
        for _ in range(runs):  # interleaved
            tb.append(up(True))
            tj.append(up(False))
            ta.append(add_in_process())
        t_bin, t_json, t_add = map(statistics.median, (tb, tj, ta))
        line(f"upload {args.upload} rays, end to end", "JSON", t_json, ".npy", t_bin,
             t_json / t_bin, ">= 5x")
        # what the transport costs: end to end minus the server's own insert time
        # (Server-Timing header), per upload, medians
        ov_j = statistics.median(t - i for t, i in zip(tj, inserts[False]))
        ov_b = statistics.median(t - i for t, i in zip(tb, inserts[True]))
        line("  ingest = end to end - insert", "JSON", ov_j, ".npy", ov_b, ov_j / ov_b, ">= 5x")
        print(f"  server insert (Field.add_rays) {statistics.median(inserts[True]):.4f} s; "
              f"in-process Field.add_rays of the same batch {t_add:.4f} s")

        # 3. small concurrent queries --------------------------------------------
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        per = max(1, args.clients // args.procs)
        rates, p50s, p99s = [], [], []
        for _ in range(3):
            q = ctx.Queue()
            ps = [ctx.Process(target=_small_client, args=(url, args.seconds, per, q))
                  for _ in range(args.procs)]
            for p in ps:
                p.start()
            lat = []
            for _ in ps:
                lat += q.get()
            for p in ps:
                p.join()
            rates.append(len(lat) / args.seconds)
            p50s.append(np.percentile(lat, 50) * 1e3)
            p99s.append(np.percentile(lat, 99) * 1e3)
        rate = statistics.median(rates)
        small = paper_rays(np.random.default_rng(3), 4)
        single = timed(lambda: ref.query_rays(*small, threads=1), 200)
        print(f"small queries (1-8 rays), {per * args.procs} concurrent clients in "
              f"{args.procs} processes: {rate:,.0f} queries/s "
              f"(target >= 1000), p50 {statistics.median(p50s):.2f} ms, "
              f"p99 {statistics.median(p99s):.2f} ms; in-process call {single * 1e3:.3f} ms")
    finally:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
