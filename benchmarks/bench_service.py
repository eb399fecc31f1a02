"""Service vs in-process Field on the same data (issue 4 targets).

1. 250,000-ray query: binary (.npy) round trip over loopback vs the in-process
   ``Field.query_rays`` call            -> ratio, target <= 1.3x
2. upload of one batch: binary (.npy) vs the same batch as JSON
   a. ingestion = time to the acknowledgement with ``?wait=false`` (batch
      validated, coordinates computed, committed to SQLite with
      synchronous=FULL; the Delaunay insert follows in the background and is
      awaited, untimed, before the next run)  -> ratio, target >= 5x
   b. end to end with ``?wait=true`` (acknowledged once also triangulated),
      next to the in-process ``Field.add_rays``: the insert dominates both
3. small queries (1-8 rays) from a concurrent client: ``wrk`` (C, keep-alive,
   ``--clients`` connections; the Python thread client if wrk is absent)
                                        -> queries/s (target >= 1000), p50/p99;
   also through the FastAPI route (what the lean path bypasses)

A real server process (``python -m flatserve.service``) on a free loopback port
with a temporary data dir. Medians of several runs.

    .venv/bin/python benchmarks/bench_service.py [--samples 20000] [--queries 250000]
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import orjson

from timing import median_time  # first: the repository root on sys.path (tests.harness)
from flatserve.client import Client
from tests.harness.process import free_port
from flatserve.field import Field
from flatserve.service.rooms import specs
from flatserve.service.server import limit_blas_threads

#: The paper's single chart, as the in-process reference (a field without `basis` is
#: an atlas; its figures are the atlas benchmarks').
ONE_CHART = {"kind": "tangent_simplex"}


def paper_rays(rng, n):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


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


def _small_client(url, query, seconds, threads, q):
    """One client process: ``threads`` keep-alive clients querying 1-8 rays each."""
    import httpx

    small = [paper_rays(np.random.default_rng(i), int(1 + i % 8)) for i in range(64)]
    bodies = [orjson.dumps({"origins": o, "directions": v}, option=orjson.OPT_SERIALIZE_NUMPY)
              for o, v in small]
    lat, stop = [], threading.Event()

    def worker(k):
        with httpx.Client(base_url=url) as cl:
            i = k * 31
            while not stop.is_set():
                t0 = time.perf_counter()
                r = cl.post(f"/v1/fields/bench/query{query}", content=bodies[i % len(bodies)],
                            headers={"Content-Type": "application/json"})
                lat.append(time.perf_counter() - t0)
                assert r.status_code == 200
                i += 1

    ts = [threading.Thread(target=worker, args=(k,)) for k in range(threads)]
    for t in ts:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in ts:
        t.join()
    q.put(lat)


def small_queries_threads(url, query, args):
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    per = max(1, args.clients // args.procs)
    rates, p50s, p99s = [], [], []
    for _ in range(3):
        q = ctx.Queue()
        ps = [ctx.Process(target=_small_client, args=(url, query, args.seconds, per, q))
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
    return statistics.median(rates), statistics.median(p50s), statistics.median(p99s)


_WRK_LUA = """
local bodies = {%s}
local n, i = #bodies, 0
local path = "%s"
local headers = {["Content-Type"] = "application/json"}
request = function()
  i = i + 1
  return wrk.format("POST", path, headers, bodies[(i %% n) + 1])
end
response = function(status, hdrs, body)
  if status ~= 200 then error("status " .. status) end
end
"""


def _wrk_ms(text: str) -> float:
    m = re.fullmatch(r"([\d.]+)(us|ms|s|m)", text)
    return float(m.group(1)) * {"us": 1e-3, "ms": 1.0, "s": 1e3, "m": 6e4}[m.group(2)]


def small_queries_wrk(wrk, url, query, bodies, args):
    """wrk (one thread, ``args.clients`` keep-alive connections), 3 runs, medians."""
    lua = _WRK_LUA % (", ".join("[=[" + b.decode() + "]=]" for b in bodies),
                      f"/v1/fields/bench/query{query}")
    with tempfile.NamedTemporaryFile("w", suffix=".lua", delete=False) as fh:
        fh.write(lua)
    rates, p50s, p99s = [], [], []
    try:
        for _ in range(3):
            out = subprocess.run(
                [wrk, "-t1", f"-c{args.clients}", f"-d{args.seconds:g}s", "--latency", "-s",
                 fh.name, url], capture_output=True, text=True, check=True).stdout
            if "Non-2xx" in out or "errors:" in out:
                raise RuntimeError(f"wrk saw failed requests:\n{out}")
            rates.append(float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1)))
            p50s.append(_wrk_ms(re.search(r"\s50%\s+(\S+)", out).group(1)))
            p99s.append(_wrk_ms(re.search(r"\s99%\s+(\S+)", out).group(1)))
    finally:
        os.unlink(fh.name)
    return statistics.median(rates), statistics.median(p50s), statistics.median(p99s)


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
    ap.add_argument("--clients", type=int, default=8, help="concurrent small-query connections")
    ap.add_argument("--procs", type=int, default=2,
                    help="client processes sharing them (Python client, without wrk)")
    args = ap.parse_args(argv)
    # the server caps NumPy's BLAS at one thread (Settings.blas_threads): so does the
    # in-process peer, or its thin products would spin BLAS threads on the shared cores
    limit_blas_threads(1)
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
        c.create_field("bench", channels=C, basis=ONE_CHART)  # as `ref`: one chart
        c.upload_rays("bench", o, v, val)
        assert c.describe("bench")["nsamples"] == ref.nsamples
        print(f"field: {ref.nsamples} samples (k=1, d=3, {C} channels), "
              f"server and in-process built from the same rays; NumPy BLAS on 1 thread in both")

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
        counter = iter(range(10**6))

        def fresh():
            name = f"up{next(counter)}"
            c.create_field(name, channels=C, basis=ONE_CHART)
            return name

        def ack(binary):
            """Seconds to the acknowledgement of a wait=false upload (indexing untimed)."""
            name = fresh()
            t0 = time.perf_counter()
            rep = c.upload_rays(name, uo, uv, uval, binary=binary, wait=False)
            dt = time.perf_counter() - t0
            assert not rep["indexed"] or rep["accepted"] == 0
            c.wait_indexed(name, timeout=3600)  # idle server for the next run
            c.delete_field(name)
            return dt

        def end_to_end(binary):
            name = fresh()
            t0 = time.perf_counter()
            c.upload_rays(name, uo, uv, uval, binary=binary)
            dt = time.perf_counter() - t0
            c.delete_field(name)
            return dt

        def add_in_process():
            t0 = time.perf_counter()
            Field(specs.build_basis(None, 1, 3), channels=C).add_rays(uo, uv, uval)
            return time.perf_counter() - t0

        ack(True)  # warm-up (thread pools, page cache)
        ab, aj = [], []
        for _ in range(args.runs):  # interleaved
            ab.append(ack(True))
            aj.append(ack(False))
        a_bin, a_json = statistics.median(ab), statistics.median(aj)
        line(f"ingest {args.upload} rays (wait=false ack)", "JSON", a_json, ".npy", a_bin,
             a_json / a_bin, ">= 5x")
        print(f"  ack throughput: .npy {args.upload / a_bin:,.0f} rays/s, JSON "
              f"{args.upload / a_json:,.0f} rays/s (stored durably + coordinates; "
              f"triangulated afterwards in the background)")
        runs = max(2, args.runs // 2)
        tb, tj, ta = [], [], []
        for _ in range(runs):  # interleaved
            tb.append(end_to_end(True))
            tj.append(end_to_end(False))
            ta.append(add_in_process())
        t_bin, t_json, t_add = map(statistics.median, (tb, tj, ta))
        line(f"upload {args.upload} rays (wait=true e2e)", "JSON", t_json, ".npy", t_bin,
             t_json / t_bin, "none: insert-bound")
        print(f"  in-process Field.add_rays of the same batch {t_add:.4f} s "
              f"(.npy end to end / in-process {t_bin / t_add:.2f}x)")

        # 3. small concurrent queries --------------------------------------------
        small = paper_rays(np.random.default_rng(3), 4)
        single = median_time(lambda: ref.query_rays(*small, threads=1), 200)[0]
        bodies = [orjson.dumps({"origins": o, "directions": v}, option=orjson.OPT_SERIALIZE_NUMPY)
                  for o, v in (paper_rays(np.random.default_rng(i), 1 + i % 8)
                               for i in range(64))]
        wrk = shutil.which("wrk")
        for label, query in (("lean path", ""), ("FastAPI route", "?via=fastapi")):
            if wrk:
                rate, p50, p99 = small_queries_wrk(wrk, url, query, bodies, args)
                client = f"wrk, {args.clients} connections"
            else:
                rate, p50, p99 = small_queries_threads(url, query, args)
                client = (f"{args.clients} Python threads in {args.procs} processes "
                          f"(wrk not installed: apt-get install wrk)")
            print(f"small queries (1-8 rays, JSON), {label}: {rate:,.0f} queries/s "
                  f"(target >= 1000), p50 {p50:.2f} ms, p99 {p99:.2f} ms [{client}, median of "
                  f"3 x {args.seconds:g} s]; in-process call {single * 1e3:.3f} ms")
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
