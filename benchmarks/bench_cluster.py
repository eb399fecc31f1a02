"""Cluster mode on this machine: 2 Ray nodes of 1 CPU each against one process on one core.

Same run, same data, both on one throwaway PostgreSQL (tests/harness):

* the peer: a lone server (``flatserve serve``, ``shard_threads=1``, pinned to one
  core with ``taskset``) that holds its fields itself;
* ours: a front (``serve --ray``) over a real Ray cluster on loopback: a head that
  holds no shard (no memory resource) and two worker nodes of 1 CPU each, their
  shard actors at niceness 0 like the peer (``RAY_worker_niceness``,
  tests/harness/raycluster.py); ``ray_shards=2`` (one shard group per node).

The field is the demo's: rays from eyes all around the bunny
(:func:`flatserve.lightfield.sampling.orbit_samples`), an oriented covering atlas
(32 charts), RGB values. For each of ``--runs`` runs (fields created anew,
interleaved peer / ours):

1. ingest: every ray uploaded in batches of 50,000 (``wait=false``), timed from
   the first upload (once the field's shard actors are up) until a query with
   ``min_position`` of the last batch answers (every batch applied everywhere);
   also from the create, the actors' start included       -> target >= 1.5x
2. memory (first run): each node's shard processes' resident memory against the
   lone server's (its growth: the field; and its whole)    -> target <= 0.6x
3. small queries: ``--small`` queries of 1 ray and of 10 rays (from eyes all
   around: one shard group, or both) through HTTP, p50 / p99 of both; the
   difference is what the Ray hop adds                    -> target <= 3 ms at p50

Every answer of the front is checked equal (bits) to the lone server's.

``--tiles N``: the field is instead the paper's Fig. 11 set-up, one chart (rays of
the bunny from eyes in front of it, ``sample_scene``), created with ``"tiles": N``
on the cluster (each tile a Ray actor, on the worker nodes) and unsplit on the
lone server (today's one-chart field); ``--rays`` rounded to a square.

    .venv/bin/python benchmarks/bench_cluster.py [--rays 400000] [--runs 3] [--small 300]
    .venv/bin/python benchmarks/bench_cluster.py --tiles 2 [--rays 400000] [--runs 3]
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)
from flatserve.client import Client, ServiceError
from flatserve.lightfield.camera import paper_samples, sphere_samples
from flatserve.lightfield.sampling import BASIS_SCALE, bunny_scene, orbit_samples, sample_scene
from flatserve.service.demo import DEMO_REQUEST
from tests.harness.pgcluster import PgCluster
from tests.harness.process import ServerProcess
from tests.harness.raycluster import GiB, RayNodes

BATCH = 50_000


def rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def ingest(url: str, name: str, o, d, v, create: dict) -> tuple[float, float]:
    """Create ``name`` (``create``: the request) and upload every ray: seconds from
    the create, and from the first upload once the field's shards are up, until
    every batch is applied."""
    with Client(url, retries=0, timeout=600) as c:
        with contextlib.suppress(ServiceError):
            c.delete_field(name)
        t_create = time.perf_counter()
        c.create_field(name, **create)
        while not all(g["live"] == g["copies"] for g in c.describe(name).get("shard_groups")
                      or []):
            time.sleep(0.1)  # the shard actors start (a lone server has none)
        t0 = time.perf_counter()
        pos = 0
        for i in range(0, len(o), BATCH):
            pos = c.upload_rays(name, o[i:i + BATCH], d[i:i + BATCH], v[i:i + BATCH],
                                wait=False)["position"]
        while True:
            try:
                c.query_rays(name, o[:10], d[:10], min_position=pos)
                t1 = time.perf_counter()
                return t1 - t_create, t1 - t0
            except ServiceError as exc:  # the shards catching up: 503 after the wait
                if exc.status != 503:
                    raise


def small_queries(url: str, name: str, q, n: int, rays: int) -> list[float]:
    out = []
    with Client(url, retries=0, timeout=60) as c:
        for i in range(n):
            j = (i * rays) % (len(q.origins) - rays)
            t0 = time.perf_counter()
            c.query_rays(name, q.origins[j:j + rays], q.directions[j:j + rays])
            out.append(time.perf_counter() - t0)
    return out


def pct(xs, p):
    return float(np.percentile(np.asarray(xs) * 1e3, p))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=400_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--small", type=int, default=300, help="small queries timed")
    ap.add_argument("--tiles", type=int, default=0,
                    help="the Fig. 11 one-chart field, in this many tiles on the cluster")
    args = ap.parse_args()
    scene = bunny_scene()
    if args.tiles:
        side = int(round(args.rays ** 0.5))
        samples, values = sample_scene(scene, side, seed=0)
        perm = np.random.default_rng(0).permutation(len(values))
        o, d, values = samples.origins[perm], samples.directions[perm], values[perm]
        args.rays = len(o)
        q = paper_samples(141, np.random.default_rng(1))
        one = {"basis": {"kind": "tangent_simplex", "scale": BASIS_SCALE}, "channels": 3}
        create_lone, create_ray = {**one, "tiles": 1}, {**one, "tiles": args.tiles}
        print(f"the Fig. 11 field (one chart): {args.tiles} tiles on the cluster, unsplit on "
              "the lone server")
    else:
        samples, values = orbit_samples(scene, args.rays, seed=0)
        o, d = samples.origins, samples.directions
        q = sphere_samples(20_000, np.random.default_rng(1))
        create_lone = create_ray = {**{k: v for k, v in DEMO_REQUEST.items()
                                       if k != "channels"}, "channels": 3}
    v = np.repeat(values, 3, axis=1) if values.shape[1] == 1 else values
    opts = dict(snapshot_every=0, read_wait_timeout=600, apply_wait_timeout=600,
                log_level="warning")
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        tmp = Path(tmp)
        pg = stack.enter_context(PgCluster(fsync=False))
        t0 = time.perf_counter()
        nodes = stack.enter_context(RayNodes(workers=2, cpus=1, memory=8 * GiB, head_memory=0))
        print(f"Ray: a head and 2 worker nodes of 1 CPU on loopback, up in "
              f"{time.perf_counter() - t0:.1f} s")
        lone = stack.enter_context(ServerProcess(
            tmp / "lone", tmp / "lone.log", command=["taskset", "-c", "0", sys.executable,
                                                     "-m", "flatserve.service"],
            database_url=pg.create_database("lone"), shard_threads=1, **opts))
        front = stack.enter_context(ServerProcess(
            tmp / "front", tmp / "front.log", database_url=pg.create_database("ray"),
            ray=nodes.address, ray_shards=2, **opts))
        lone.wait_ready(120)
        front.wait_ready(120)
        base = rss(lone.proc.pid)
        ts_lone, ts_ray, all_lone, all_ray, mem = [], [], [], [], None
        for run in range(args.runs):
            whole, t = ingest(lone.url, "f", o, d, v, create_lone)
            all_lone.append(whole)
            ts_lone.append(t)
            grown = rss(lone.proc.pid)
            whole, t = ingest(front.url, "f", o, d, v, create_ray)
            all_ray.append(whole)
            ts_ray.append(t)
            print(f"run {run + 1}: ingest of {args.rays:,} rays: one process on one core "
                  f"{ts_lone[-1]:.1f} s, 2 Ray nodes {ts_ray[-1]:.1f} s (from the create, the "
                  f"shards' start included: {all_lone[-1]:.1f} s, {all_ray[-1]:.1f} s)",
                  flush=True)
            if mem is None:
                time.sleep(2.5)  # two status rounds
                with Client(front.url) as c:
                    groups = c.describe("f")["shard_groups"]
                per_node: dict = {}
                for g in groups:
                    per_node[g["node"]] = per_node.get(g["node"], 0) + (g["memory"] or 0)
                    for t in g.get("tiles") or ():  # a field in tiles: each tile's actor
                        per_node[t["node"]] = per_node.get(t["node"], 0) + t["memory"]
                mem = (grown, grown - base, per_node)
            # the answers are the lone server's, bit for bit
            with Client(lone.url) as a, Client(front.url) as b:
                x = a.query_rays("f", q.origins, q.directions)
                y = b.query_rays("f", q.origins, q.directions)
            assert np.array_equal(x.values, y.values, equal_nan=True), "answers differ"
        lat = {k: (small_queries(lone.url, "f", q, args.small, k),
                   small_queries(front.url, "f", q, args.small, k)) for k in (1, 10)}
    m_lone, m_field, per_node = mem
    print()
    print(f"ingest (median of {args.runs}): one process on one core "
          f"{statistics.median(ts_lone):.1f} s, 2 Ray nodes of 1 CPU "
          f"{statistics.median(ts_ray):.1f} s: {statistics.median(ts_lone) / statistics.median(ts_ray):.2f}x"
          " (target >= 1.5x); from the create, the shard actors' start included: "
          f"{statistics.median(all_lone):.1f} s, {statistics.median(all_ray):.1f} s: "
          f"{statistics.median(all_lone) / statistics.median(all_ray):.2f}x")
    print(f"memory: the lone server {m_lone / 2**20:,.0f} MiB resident ({m_field / 2**20:,.0f} MiB"
          " for the field)")
    for node, b in sorted(per_node.items()):
        print(f"  node {node[:8]}: shard processes {b / 2**20:,.0f} MiB = "
              f"{b / m_lone:.2f}x the lone server ({b / m_field:.2f}x its field) (target <= 0.6x)")
    for k, (lat_lone, lat_ray) in lat.items():
        print(f"small queries ({k} ray{'s' if k > 1 else ''} from anywhere, {args.small} each): one "
              f"process p50 {pct(lat_lone, 50):.2f} ms p99 {pct(lat_lone, 99):.2f} ms; Ray p50 "
              f"{pct(lat_ray, 50):.2f} ms p99 {pct(lat_ray, 99):.2f} ms; the hop adds "
              f"{pct(lat_ray, 50) - pct(lat_lone, 50):.2f} ms at p50 (target <= 3 ms)")
    print("every answer of the front equal (bits) to the lone server's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
