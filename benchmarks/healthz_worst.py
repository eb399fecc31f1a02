"""/healthz while the largest requests the default limits admit run at once.

A real server (default settings; ``--max-json-bytes`` to try another) with an
8-channel field: three 1M-ray ``.npy`` queries, two JSON queries of the largest
body ``max_json_bytes`` admits and two projections at the 64 MiB JSON answer
limit, each sent twice, while a client asks ``/healthz`` every 50 ms: its p50,
p99 and maximum latency (the bound the service keeps: 1 s).

    .venv/bin/python benchmarks/healthz_worst.py [--max-json-bytes N] [--runs 3]
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

import timing  # noqa: F401  (the repository root on sys.path, for tests.harness)
from flatserve.client import Client
from flatserve.service import Settings
from flatserve.service.http import codec
from tests.harness.process import ServerProcess

MiB = 1 << 20


def rays(rng, n):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def largest_json_query(q, limit: int) -> tuple[bytes, int]:
    """The JSON query body of the most rows of ``q`` under ``limit`` bytes."""
    def body(n):
        return json.dumps({"origins": q[0][:n].tolist(), "directions": q[1][:n].tolist()}).encode()

    n = 1000
    while len(body(n)) < 0.95 * limit:
        n = int(n * 1.3)
    while len(body(n)) > limit - 1024:
        n = int(n * 0.97)
    return body(n), n


def one_run(limit: int, max_json_bytes: int | None, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    tmp = Path(tempfile.mkdtemp())
    opts = {"snapshot_every": 0}
    if max_json_bytes:
        opts["max_json_bytes"] = max_json_bytes
    with ServerProcess(tmp / "data", tmp / "s.log", **opts) as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            c.create_field("f", channels=8)
            o, v = rays(rng, 20_000)
            c.upload_rays("f", o, v, rng.uniform(size=(20_000, 8)))
        q = rays(rng, 1_000_000)
        npy = codec.npy_bytes(np.c_[q[0], q[1]])
        jq, n = largest_json_query(q, limit)
        proj_rows = (64 * MiB) // (82 * codec.JSON_BYTES_PER_NUMBER)
        proj = {"k": 0, "d": 8, "flats": {"Q": np.broadcast_to(np.eye(8), (2, 8, 8)).tolist(),
                                          "r": np.zeros((2, 8)).tolist()},
                "weights": np.full((proj_rows, 2), 0.5).tolist()}
        jobs = [("/v1/fields/f/query", dict(content=npy, headers={"content-type": codec.NPY,
                                                                  "accept": codec.NPY}))] * 3
        jobs += [("/v1/fields/f/query", dict(content=jq, headers={"content-type": codec.JSON}))] * 2
        jobs += [("/v1/math/project", dict(json=proj))] * 2
        statuses: list = []

        def run(path, kw):
            with httpx.Client(base_url=srv.url, timeout=600) as h:
                for _ in range(2):
                    statuses.append(h.post(path, **kw).status_code)

        threads = [threading.Thread(target=run, args=job) for job in jobs]
        lat = []
        with httpx.Client(base_url=srv.url, timeout=60) as h:
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                t0 = time.perf_counter()
                h.get("/healthz").raise_for_status()
                lat.append(time.perf_counter() - t0)
                time.sleep(0.05)
        for t in threads:
            t.join()
    return {"rows": n, "body": len(jq), "statuses": sorted(set(statuses)), "lat": lat}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-json-bytes", type=int, default=None)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    limit = args.max_json_bytes or Settings().max_json_bytes
    print(f"max_json_bytes {limit / MiB:.0f} MiB; load average {os.getloadavg()[0]:.1f}")
    for i in range(args.runs):
        r = one_run(limit, args.max_json_bytes, i)
        lat = np.array(r["lat"])
        print(f"run {i + 1}: JSON query body {r['body'] / MiB:.1f} MiB ({r['rows']:,} rows), "
              f"answers {r['statuses']}; /healthz n={lat.size} p50 {np.median(lat):.3f} s, "
              f"p99 {np.quantile(lat, 0.99):.3f} s, max {lat.max():.3f} s (bound 1 s)",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
