"""One chart over tiles (Tile & Merge, issue 19): tiles against the unsplit chart, same run.

The paper's Fig. 11 field: ``--side``^2 rays of the bunny (1,000^2 = 1M), the
paper's basis (one chart), in random order, added in batches of 100,000 as
``flatserve lightfield`` builds it. Each configuration runs in a process of
its own, pinned with ``taskset`` to its cores, interleaved, medians of
``--runs``:

1. build (chart + insert of every ray): 2 tiles on 2 cores against the unsplit
   field on 2 cores                                  -> target >= 1.6x;
   and 2 tiles on 1 core against the unsplit on 1 core (no slower: >= 1.0x)
2. query throughput of ``--queries`` rays of the same sampling, on one thread
   (forwarding included), tiled against unsplit        -> target >= 0.8x;
   the share of queries forwarded to another tile
3. memory: per tile count of ``--halo``, the halo (foreign points held) over
   own points, the exchange rounds, the process's resident memory

``--ray``: only the build and the queries of 2 tiles each in a Ray actor of its
own, on the two worker nodes (1 CPU each) of a cluster on loopback (cluster
mode's tiles: ``flatserve/service/cluster/worker/tiles.py``; the building process keeps
the bookkeeping and routes the exchange), against 2 tiles in one process and the
unsplit field, on this machine's 2 cores; the answers checked equal (bits); the
exchange's rounds and the bytes it moved between the building process and the
tiles' actors, in all and per batch.

``--sizes S ...``: only the build of 2 tiles against the unsplit field on 2
cores at S^2 rays each (where tiles start to pay: ``tiles="auto"``,
``flatserve.tiles.AUTO_MIN_SAMPLES``).

Every tiled answer is checked equal (bits) to the unsplit field's.

    .venv/bin/python benchmarks/bench_tiles.py [--side 1000] [--runs 3] [--halo 2 4 8 16]
    .venv/bin/python benchmarks/bench_tiles.py --halo-only [--side 1000] [--halo 2 4 8 16]
    .venv/bin/python benchmarks/bench_tiles.py --sizes 150 224 316 447 [--runs 3]
    .venv/bin/python benchmarks/bench_tiles.py --ray [--side 632] [--runs 3]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)

BATCH = 100_000


def rss() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


def one(side: int, tiles: int | str, cores: int, queries: int, out: str,
        ray_address: str | None = None) -> dict:
    """Build and query in this process (pinned by the parent); a JSON line. With
    ``ray_address``, the tiles live in Ray actors on that cluster."""
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.lightfield.camera import paper_samples
    from flatserve.lightfield.sampling import BASIS_SCALE, bunny_scene, sample_scene
    from flatserve.parallel import set_shard_threads

    set_shard_threads(cores)
    samples, values = sample_scene(bunny_scene(), side, seed=0)
    perm = np.random.default_rng(0).permutation(len(values))
    o, d, v = samples.origins[perm], samples.directions[perm], values[perm]
    host = None
    if ray_address:
        import ray

        from flatserve.service.cluster.worker.tiles import RayTileHost
        from flatserve.service.settings import Settings
        from flatserve.tiles import hosting

        ray.init(address=ray_address, log_to_driver=False)
        host = RayTileHost(Settings(ray_shard_memory=2 << 30, shard_threads=1))
        with hosting(host):
            field = Field(Basis.around_axis(axis=2, scale=BASIS_SCALE), channels=v.shape[1],
                          tiles=tiles)
    else:
        field = Field(Basis.around_axis(axis=2, scale=BASIS_SCALE), channels=v.shape[1],
                      tiles=tiles)
    t0 = time.perf_counter()
    for i in range(0, len(o), BATCH):
        field.add(Flats.from_rays(o[i:i + BATCH], d[i:i + BATCH]), v[i:i + BATCH])
    t1 = time.perf_counter()
    field.settle()  # the tiles' exchange (left pending by the adds) belongs to the build
    build = time.perf_counter() - t0
    exchange = time.perf_counter() - t1
    q = paper_samples(int(queries ** 0.5), np.random.default_rng(1))
    qf = Flats.from_rays(q.origins, q.directions)
    chart = field.chart(qf, threads=1)
    set_shard_threads(1)
    ts = []
    for _ in range(3):
        t0 = time.perf_counter()
        res = field.query(chart, threads=1)
        ts.append(time.perf_counter() - t0)
    np.save(out, res.values)
    tri = field.triangulation
    info = {"build_s": build, "exchange_s": exchange, "query_s": statistics.median(ts),
            "queries": len(qf),
            "samples": field.nsamples, "rss": rss()}
    if tiles != 1:
        info.update(halo=tri.halo.tolist(), own=tri.own_counts.tolist(),
                    star_halo=tri.star_halo().tolist(),
                    rounds=tri.stats.rounds, retiled=tri.stats.retiled,
                    forwarded=tri.stats.forwarded / (3 * len(qf)))
    if host is not None:
        where = host.placement()
        info.update(tile_nodes=len({w["node"] for w in where}),
                    tile_rss=[w["memory"] for w in where],
                    # what the exchange moved between this process and the tiles' actors
                    exchanged=host.exchanged, batches=-(-len(o) // BATCH))
    return info


def scan_costs(n: int, runs: int) -> None:
    """The exchange's two ways of finding the cells an insert made (flatserve.tiles
    SCAN_SHARE): a walk around each new vertex (``seeds``) against one pass over
    every cell stamped with its insert (``since``), after k new points on n, in a
    tile of the Fig. 11 field's kind (4-D points of the paper's rays); the same
    cells' answers, checked equal. One thread, medians of ``runs``."""
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.triangulation import Triangulation

    rng = np.random.default_rng(0)
    basis = Basis.around_axis(axis=2, scale=1.0)
    o = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (2 * n, 3))
    s = np.c_[rng.uniform(-1, 1, (2 * n, 2)), np.zeros(2 * n)]
    pts = Field(basis).chart(Flats.from_rays(o, s - o)).points
    lo, hi = np.quantile(pts, 0.5, axis=0)[None].repeat(2, 0), pts.max(0)[None].repeat(2, 0)
    lo[0] = pts.min(0)  # group 0: the tile's own (skipped); group 1: the upper half in x0
    hi[0, 0] = lo[1, 0] = np.median(pts[:, 0])
    lo[1, 1:] = pts.min(0)[1:]
    start = np.array([0, 1, 2])
    print(f"the exchange's scan, one tile of {n:,} 4-D points of the paper's rays:")
    for share in (0.005, 0.01, 0.02, 0.05, 0.1):
        k = int(share * n)
        walk, one_pass = [], []
        for _ in range(runs):
            tri = Triangulation(4)
            tri.insert(pts[:n])
            g = tri.generation
            tri.insert(pts[n:n + k])
            own = np.ones(n + k, np.uint8)
            seeds = np.arange(n, n + k)
            t0 = time.perf_counter()
            a = tri.conflicts(own, lo, hi, start, skip=0, seeds=seeds)
            t1 = time.perf_counter()
            b = tri.conflicts(own, lo, hi, start, skip=0, since=g)
            t2 = time.perf_counter()
            assert all(np.array_equal(x, y) for x, y in zip(a, b)), "the two ways differ"
            walk.append(t1 - t0)
            one_pass.append(t2 - t1)
        w, p = statistics.median(walk), statistics.median(one_pass)
        print(f"  k = {share:5.1%} of n ({k:,} new points): walk {w:.3f} s, one pass "
              f"{p:.3f} s: the pass {w / p:.2f}x the walk's speed")


def sizes(args) -> None:
    """The build of 2 tiles against the unsplit field on 2 cores, per size."""
    print(f"Fig. 11 field in batches of {BATCH:,}: 2 tiles against the unsplit field, both "
          f"on 2 cores, medians of {args.runs}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for side in args.sizes:
            got: dict = {1: [], 2: []}
            for _ in range(args.runs):
                for tiles in (1, 2):
                    got[tiles].append(run(args, tiles, 2, str(Path(tmp) / "s.npy"), side=side,
                                          queries=10_000)["build_s"])
            a, b = statistics.median(got[1]), statistics.median(got[2])
            print(f"  {side ** 2:>9,} rays: unsplit {a:6.2f} s, 2 tiles {b:6.2f} s: {a / b:.2f}x",
                  flush=True)


def auto_on_one_core(args) -> None:
    """tiles="auto" on one core (where it keeps one tile) against the unsplit field."""
    print(f'Fig. 11 field: {args.side ** 2:,} rays, tiles="auto" against the unsplit field, '
          f"both on one core, medians of {args.runs}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        got: dict = {1: [], "auto": []}
        for _ in range(args.runs):
            for tiles in (1, "auto"):
                x = run(args, tiles, 1, str(Path(tmp) / f"{tiles}.npy"))
                got[tiles].append(x["build_s"])
                print(f"  {tiles}: build {x['build_s']:.1f} s"
                      + (f" ({len(x['own'])} tile)" if "own" in x else ""), flush=True)
            assert np.array_equal(np.load(str(Path(tmp) / "1.npy")),
                                  np.load(str(Path(tmp) / "auto.npy")), equal_nan=True)
        a, b = statistics.median(got[1]), statistics.median(got["auto"])
        print(f'build on one core: unsplit {a:.1f} s, tiles="auto" {b:.1f} s: {a / b:.2f}x '
              f"(target >= 1.0x); the same answers (bits)")


def in_actors(args) -> None:
    """2 tiles in Ray actors on two nodes against 2 tiles in one process and unsplit."""
    from tests.harness.raycluster import GiB, RayNodes

    print(f"Fig. 11 field: {args.side ** 2:,} rays in batches of {BATCH:,}; 2 tiles each in a "
          f"Ray actor (two worker nodes of 1 CPU, loopback) against 2 tiles in one process and "
          f"the unsplit field, all on this machine's {os.cpu_count()} cores; medians of "
          f"{args.runs}", flush=True)
    with tempfile.TemporaryDirectory() as tmp, \
            RayNodes(workers=2, cpus=1, memory=8 * GiB, head_memory=0) as nodes:
        ref = str(Path(tmp) / "ref.npy")
        res: dict = {}
        for r in range(args.runs):
            for key in ("unsplit", "2 tiles", "2 tiles in actors"):
                out = ref if key == "unsplit" else str(Path(tmp) / f"{key[-6:]}.npy")
                x = run(args, 1 if key == "unsplit" else 2, 2, out,
                        ray=nodes.address if key.endswith("actors") else None)
                res.setdefault(key, []).append(x)
                if out != ref:
                    assert np.array_equal(np.load(out), np.load(ref), equal_nan=True), \
                        f"{key}: answers differ from the unsplit field's"
                extra = (f", tiles on {x['tile_nodes']} nodes, their resident memory "
                         f"{[round(m / 2**30, 2) for m in x['tile_rss']]} GiB; the exchange: "
                         f"{x['rounds']} rounds, {x['exchanged'] / 2**20:.1f} MiB between this "
                         f"process and the tiles ({x['exchanged'] / x['batches'] / 2**20:.1f} "
                         f"MiB a batch of {BATCH:,})"
                         if "tile_rss" in x else "")
                print(f"run {r + 1}: {key}: build {x['build_s']:.1f} s, query "
                      f"{x['queries'] / x['query_s']:,.0f}/s, this process's peak "
                      f"{x['rss'] / 2**30:.2f} GiB{extra}", flush=True)
        med = {k: (statistics.median(x["build_s"] for x in v),
                   statistics.median(x["queries"] / x["query_s"] for x in v))
               for k, v in res.items()}
        a = med["unsplit"]
        print()
        for key in ("2 tiles", "2 tiles in actors"):
            b = med[key]
            print(f"{key}: build {b[0]:.1f} s against unsplit {a[0]:.1f} s: {a[0] / b[0]:.2f}x; "
                  f"query {b[1]:,.0f}/s against {a[1]:,.0f}/s: {b[1] / a[1]:.2f}x")
        print("every answer equal (bits) to the unsplit field's")


def run(args, tiles: int | str, cores: int, out: str, *, side: int | None = None,
        queries: int | None = None, ray: str | None = None) -> dict:
    cpus = ",".join(str(c) for c in range(cores))
    cmd = ["taskset", "-c", cpus, sys.executable, __file__, "--one", str(tiles), "--cores",
           str(cores), "--side", str(side or args.side), "--queries",
           str(queries or args.queries), "--out", out, *(["--ray-address", ray] if ray else [])]
    got = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(got.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=1000, help="rays: side^2")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--queries", type=int, default=250_000)
    ap.add_argument("--halo", type=int, nargs="*", default=[2, 4, 8, 16])
    ap.add_argument("--halo-only", action="store_true",
                    help="only the halo per tile count of --halo (each on 2 cores), against "
                         "the unsplit field's answers")
    ap.add_argument("--scan", type=int, metavar="N",
                    help="only the exchange's scan costs on a tile of N points")
    ap.add_argument("--sizes", type=int, nargs="+", metavar="S",
                    help="only the build at S^2 rays, 2 tiles against unsplit on 2 cores")
    ap.add_argument("--auto", action="store_true",
                    help='only tiles="auto" on one core (one tile) against the unsplit field')
    ap.add_argument("--ray", action="store_true",
                    help="only 2 tiles in Ray actors against 2 tiles in one process and unsplit")
    ap.add_argument("--ray-address", help=argparse.SUPPRESS)
    ap.add_argument("--one", type=lambda s: s if s == "auto" else int(s), help=argparse.SUPPRESS)
    ap.add_argument("--cores", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.side, args.one, args.cores, args.queries, args.out,
                             args.ray_address)))
        return 0
    if args.ray:
        in_actors(args)
        return 0
    if args.scan:
        scan_costs(args.scan, args.runs)
        return 0
    if args.sizes:
        sizes(args)
        return 0
    if args.auto:
        auto_on_one_core(args)
        return 0
    print(f"Fig. 11 field: {args.side ** 2:,} rays of the bunny in random order, batches of "
          f"{BATCH:,}; {os.cpu_count()} cores here", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        ref = str(Path(tmp) / "ref.npy")
        res: dict = {}
        if args.halo_only:
            res[(1, 2)] = [run(args, 1, 2, ref)]
        for r in range(0 if args.halo_only else args.runs):
            for key in ((1, 2), (2, 2), (1, 1), (2, 1)):
                out = ref if key == (1, 2) else str(Path(tmp) / f"t{key[0]}c{key[1]}.npy")
                res.setdefault(key, []).append(run(args, *key, out))
                if out != ref:
                    assert np.array_equal(np.load(out), np.load(ref), equal_nan=True), \
                        f"{key}: answers differ from the unsplit field's"
                x = res[key][-1]
                print(f"run {r + 1}: {key[0]} tile(s) on {key[1]} core(s): build "
                      f"{x['build_s']:.1f} s, query {x['queries'] / x['query_s']:,.0f}/s",
                      flush=True)
        med = {k: (statistics.median(x["build_s"] for x in v),
                   statistics.median(x["query_s"] for x in v)) for k, v in res.items()}
        print()
        for c, target in (() if args.halo_only else ((2, "target >= 1.6x"), (1, "target >= 1.0x"))):
            a, b = med[(1, c)][0], med[(2, c)][0]
            print(f"build on {c} core(s) (median of {args.runs}): unsplit {a:.1f} s, 2 tiles "
                  f"{b:.1f} s: {a / b:.2f}x ({target})")
        if not args.halo_only:
            a, b = med[(1, 2)][1], med[(2, 2)][1]
            fw = statistics.median(x["forwarded"] for x in res[(2, 2)])
            print(f"query throughput on one thread: unsplit {res[(1, 2)][0]['queries'] / a:,.0f}"
                  f"/s, 2 tiles {res[(2, 2)][0]['queries'] / b:,.0f}/s: {a / b:.2f}x (target "
                  f">= 0.8x); {100 * fw:.2f} % forwarded")
            print("every tiled answer equal (bits) to the unsplit field's")
        print()
        base = res[(1, 2)][0]
        print(f"halo over own points, the Fig. 11 field at {base['samples']:,} samples "
              f"(unsplit: peak resident {base['rss'] / 2**20:,.0f} MiB):")
        for T in args.halo:
            out = str(Path(tmp) / f"h{T}.npy")
            x = res[(T, 2)][0] if (T, 2) in res else run(args, T, 2, out)
            if (T, 2) not in res:
                assert np.array_equal(np.load(out), np.load(ref), equal_nan=True), \
                    f"{T} tiles: answers differ from the unsplit field's"
            halo, own, star = np.array(x["halo"]), np.array(x["own"]), np.array(x["star_halo"])
            print(f"  {T:2d} tiles: halo {100 * halo.sum() / own.sum():5.1f} % (tile max "
                  f"{100 * (halo / own).max():5.1f} %; the stars' least "
                  f"{100 * star.sum() / own.sum():5.1f} %), own points {own.min():,}-{own.max():,}, "
                  f"exchange rounds {x['rounds']} ({x['exchange_s']:.1f} s), re-tiled "
                  f"{x['retiled']}, peak resident {x['rss'] / 2**20:,.0f} MiB, build "
                  f"{x['build_s']:.1f} s, "
                  f"{100 * x['forwarded']:.2f} % of queries forwarded")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
