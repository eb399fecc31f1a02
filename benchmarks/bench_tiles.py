"""One chart over tiles (Tile & Merge, issue 19): tiles against the unsplit chart, same run.

The paper's Fig. 11 field: ``--side``^2 rays of the bunny (1,000^2 = 1M), the
paper's basis (one chart), in random order, added in batches of 100,000 as
``flatserve lightfield`` builds it. Each configuration runs in a process of
its own, pinned with ``taskset`` to its cores, interleaved, medians of
``--runs``:

1. build (chart + insert of every ray): 2 tiles on 2 cores against the unsplit
   field on 2 cores (issue 19: >= 1.6x) and on 1 core (issue 40: >= 1.7x);
   2 tiles on 1 core against the unsplit on 1 core (issue 40: >= 0.95x)
2. query throughput of ``--queries`` rays of the same sampling, on one thread
   (forwarding included), tiled against unsplit        -> target >= 0.8x;
   the share of queries forwarded to another tile
3. memory: per tile count of ``--halo``, the halo (foreign points held) over
   own points, beside the least (the stars' foreign vertices) and the points
   sent (those the receivers left out: no neighbours of their own points), the
   exchange rounds, the process's resident memory

``--ray``: only the build and the queries of 2 tiles each in a Ray actor of its
own, on the two worker nodes (1 CPU each) of a cluster on loopback (cluster
mode's tiles: ``flatserve/service/cluster/worker/tiles.py``; the building process keeps
the bookkeeping and routes the exchange), against 2 tiles in one process and the
unsplit field, on this machine's 2 cores; the answers checked equal (bits); the
exchange's rounds and the bytes it moved between the building process and the
tiles' actors, in all and per batch.

``--http``: the service (issue 40): the same field, ``--side``^2 rays (548^2 =
300,304 by default here), uploaded over HTTP in batches of ``--batch`` rows
(``wait=false``, the last ``wait=true``: every batch applied, in log order; several
sizes: a 2-core configuration each, the 1-core one with the first) to a
real server on 127.0.0.1 (a temporary SQLite data directory), timed from the
first upload to the last one's response: a server pinned to one core
(``taskset -c 0``, ``shard_threads=1``) holding the field unsplit, against one on
2 cores (``shard_threads=2``) holding it in ``"tiles": --http-tiles`` (2 or
``auto``); a fresh server for each upload, interleaved, medians of ``--runs``;
the answers to a few thousand query rays checked equal (bits, the weights and
sample ids too). ``--old DIR``: also the 2-core server run from the checkout
``DIR`` (its ``flatserve``, the extension copied in; e.g. a ``git worktree`` of
an earlier commit), interleaved with the others: before and after in one run.

``--sizes S ...``: only the build of 2 tiles against the unsplit field on 2
cores at S^2 rays each (where tiles start to pay: ``tiles="auto"``,
``flatserve.tiles.AUTO_MIN_SAMPLES``).

Every tiled answer is checked equal (bits) to the unsplit field's.

    .venv/bin/python benchmarks/bench_tiles.py [--side 1000] [--runs 3] [--halo 2 4 8 16]
    .venv/bin/python benchmarks/bench_tiles.py --halo-only [--side 1000] [--halo 2 4 8 16]
    .venv/bin/python benchmarks/bench_tiles.py --sizes 150 224 316 447 [--runs 3]
    .venv/bin/python benchmarks/bench_tiles.py --ray [--side 632] [--runs 3]
    .venv/bin/python benchmarks/bench_tiles.py --http [--side 548] [--batch 50000 [150000 ...]] [--runs 3]
        [--http-tiles 2|auto] [--old /tmp/old-checkout]
"""
from __future__ import annotations

import argparse
import itertools
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
                    sent=tri.stats.sent, left_out=tri.stats.left_out,
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


def _server_command(cores: int, src: str | None, profile: str | None = None) -> list[str]:
    """``python -m flatserve.service`` pinned to the first ``cores`` cores; from the
    checkout ``src`` (its ``flatserve`` first, not this one's editable install);
    ``profile``: timed (:func:`serve_profiled`), its events written there."""
    pin = ["taskset", "-c", ",".join(str(c) for c in range(cores))]
    if profile is not None:
        return [*pin, sys.executable, __file__, "--serve-profiled", profile]
    if src is None:
        return [*pin, sys.executable, "-m", "flatserve.service"]
    boot = ("import runpy, sys; sys.meta_path[:] = [f for f in sys.meta_path if 'editable' "
            f"not in type(f).__module__]; sys.path.insert(0, {src!r}); "
            "runpy.run_module('flatserve.service', run_name='__main__', alter_sys=True)")
    return [*pin, sys.executable, "-c", boot]


def _http_ingest(tmp: Path, label: str, cores: int, tiles, src: str | None, o, d, v, q,
                 batch: int, profile: str | None = None) -> tuple[float, dict, dict]:
    """A fresh server (``cores``, from ``src``), the field created with ``tiles`` and
    every ray uploaded: seconds from the first upload to the last one's response,
    the answers to ``q`` and the server's own figures."""
    import shutil

    from flatserve.client import Client
    from tests.harness.process import ServerProcess

    data = tmp / f"data-{label}"
    shutil.rmtree(data, ignore_errors=True)
    with ServerProcess(data, tmp / f"{label}.log", log_level="warning",
                       command=_server_command(cores, src, profile), shard_threads=cores,
                       snapshot_every=0, apply_wait_timeout=600,
                       read_wait_timeout=600) as srv:
        srv.wait_ready(120)
        with Client(srv.url, retries=0, timeout=600) as c:
            from flatserve.lightfield.sampling import BASIS_SCALE

            c.create_field("f", basis={"kind": "tangent_simplex", "scale": BASIS_SCALE},
                           channels=v.shape[1], tiles=tiles)
            t0 = time.perf_counter()
            n = len(o)
            for i in range(0, n, batch):
                last = i + batch >= n
                c.upload_rays("f", o[i:i + batch], d[i:i + batch], v[i:i + batch], wait=last)
            took = time.perf_counter() - t0
            res = c.query_rays("f", q.origins, q.directions, weights=True)
            # a cell's weights come in its vertex order, which differs between
            # triangulations: compared as (id, weight) pairs sorted by id per row; beyond
            # the hull (NaN) the facet a walk ends at is no answer: not compared
            by = np.argsort(res.ids, axis=1)
            inside = np.isfinite(res.values).all(axis=1)
            got = {"values": res.values, "inside": inside,
                   "ids": np.take_along_axis(res.ids, by, 1)[inside],
                   "weights": np.take_along_axis(res.weights, by, 1)[inside]}
            desc = c.describe("f")
    return took, got, desc


#: what ``--profile`` times in the 2-core server: (module, class or None, function, label)
PROFILED = [
    ("flatserve.service.http.codec", None, "decode", "decode"),
    ("flatserve.service.rooms.uploads", "UploadService", "upload", "upload (request)"),
    ("flatserve.service.rooms.uploads", "UploadService", "_commit_and_chart",
     "chart + pack + commit"),
    ("flatserve.service.log.sqlrules", "SQLBackend", "add_batch", "commit (SQLite)"),
    ("flatserve.service.rooms.applier", "LogApplier", "apply_batch", "apply (follower)"),
    ("flatserve.field", "Field", "insert_prepared", "insert_prepared"),
    ("flatserve.tiles", "TiledTriangulation", "_insert", "tiles: own inserts"),
    ("flatserve.tiles", "TiledTriangulation", "_exchange", "tiles: exchange"),
    ("flatserve.tiles", "Tile", "insert", None),  # own / halo, per tile thread
    ("flatserve.tiles", "Tile", "conflicts", "tile: scan"),
]


def serve_profiled(out: str, argv: list[str]) -> None:
    """The server (``python -m flatserve.service argv``) with the calls of
    :data:`PROFILED` timed: ``(label, thread, start, end, rows)`` events written
    to ``out`` (JSON) every half second."""
    import importlib
    import runpy
    import threading

    events: list = []

    def wrap(owner, name, label):
        f = getattr(owner, name)

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                lab = label or ("tile: insert own" if a[3] else "tile: insert halo")
                rows = len(a[1]) if label is None else 0
                events.append((lab, threading.current_thread().name, t0,
                               time.perf_counter(), rows))
        setattr(owner, name, timed)

    for mod, cls, name, label in PROFILED:
        m = importlib.import_module(mod)
        wrap(getattr(m, cls) if cls else m, name, label)

    def dump():
        while True:
            time.sleep(0.5)
            with open(out + ".tmp", "w") as fh:
                json.dump(list(events), fh)
            os.replace(out + ".tmp", out)

    threading.Thread(target=dump, daemon=True).start()
    sys.argv = ["flatserve.service", *argv]
    runpy.run_module("flatserve.service", run_name="__main__", alter_sys=True)


def _busy(iv) -> float:
    """Seconds covered by the union of intervals ``[(start, end)]``."""
    tot, end = 0.0, -1e300
    for a, b in sorted(iv):
        if b > end:
            tot += b - max(a, end)
            end = b
    return tot


def print_profile(path: str) -> None:
    """Where the profiled server's time went (:func:`serve_profiled`'s events)."""
    with open(path) as fh:
        ev = json.load(fh)
    if not ev:
        print("  (no events)")
        return
    t0 = min(e[2] for e in ev if e[0] == "upload (request)")
    t1 = max(e[3] for e in ev if e[0] == "apply (follower)")
    wall = t1 - t0
    print(f"  profile of the 2-core server (first upload's arrival to last apply: {wall:.2f} s):")
    labels = list(dict.fromkeys(e[0] for e in ev))
    for lab in labels:
        xs = [e for e in ev if e[0] == lab]
        threads = sorted({e[1] for e in xs})
        per = {t: sum(e[3] - e[2] for e in xs if e[1] == t) for t in threads}
        rows = sum(e[4] for e in xs)
        print(f"    {lab:24s} {len(xs):4d} calls, {sum(per.values()):7.2f} s summed, "
              f"{_busy([(e[2], e[3]) for e in xs]):7.2f} s of wall"
              + (f", {rows:,} points" if rows else "")
              + (f"; per thread {', '.join(f'{v:.2f}' for v in per.values())}"
                 if len(per) > 1 else ""))
    app = sorted((e[2], e[3]) for e in ev if e[0] == "apply (follower)")
    idle = sum(max(0.0, b[0] - a[1]) for a, b in itertools.pairwise(app)) + (
        app[0][0] - t0)
    print(f"    the follower idle (waiting for the next committed batch) {idle:.2f} s; "
          f"applying {_busy(app):.2f} s")
    ins = sorted((e[2], e[3]) for e in ev if e[0] == "insert_prepared")
    own = sorted((e[2], e[3]) for e in ev if e[0] == "tiles: own inserts")
    exch = sorted((e[2], e[3]) for e in ev if e[0] == "tiles: exchange")
    print("    per batch (s): apply = before the insert + own inserts + exchange")
    for i, (a, b) in enumerate(app):
        x = [iv for iv in ins if a <= iv[0] <= b]
        o = [iv[1] - iv[0] for iv in own if a <= iv[0] <= b]
        xx = [iv[1] - iv[0] for iv in exch if a <= iv[0] <= b]
        print(f"      {i + 1}: {b - a:6.2f} = {(x[0][0] - a) if x else 0:5.2f} + "
              f"{sum(o):6.2f} + {sum(xx):5.2f}")
    req = [(e[2], e[3]) for e in ev if e[0] == "upload (request)"]
    both = 0.0
    for a, b in req:  # request work overlapping the follower's
        for c, d in app:
            both += max(0.0, min(b, d) - max(a, c))
    print(f"    requests' work overlapping an apply {both:.2f} s of "
          f"{_busy(req):.2f} s of requests")


def over_http(args) -> None:
    """Issue 40: the Fig. 11 field uploaded over HTTP, 1-core unsplit against 2-core
    tiled servers (and, with ``--old``, the 2-core server of an earlier checkout)."""
    from flatserve.lightfield.camera import paper_samples
    from flatserve.lightfield.sampling import bunny_scene, sample_scene

    side = args.side or 548
    samples, values = sample_scene(bunny_scene(), side, seed=0)
    perm = np.random.default_rng(0).permutation(len(values))
    o, d, v = samples.origins[perm], samples.directions[perm], values[perm]
    v = np.repeat(v, 3, axis=1) if v.shape[1] == 1 else v
    q = paper_samples(60, np.random.default_rng(1))  # 3,600 query rays
    tiles = args.http_tiles
    b0 = args.batch[0]
    configs = [(f"unsplit, 1 core, batches of {b0:,}", 1, 1, None, b0)]
    for b in args.batch:
        configs.append((f"tiles {tiles}, 2 cores, batches of {b:,}", 2, tiles, None, b))
        if args.old:
            configs.append((f"tiles {tiles}, 2 cores, batches of {b:,}, {Path(args.old).name}",
                            2, tiles, args.old, b))
    print(f"Fig. 11 field over HTTP: {len(o):,} rays in batches of "
          f"{' or '.join(f'{b:,}' for b in args.batch)} rows (wait=false, "
          f"the last wait=true), a fresh server each; {os.cpu_count()} cores here; "
          f"medians of {args.runs}; load {os.getloadavg()[0]:.2f}", flush=True)
    times: dict = {c[0]: [] for c in configs}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ref = None
        if args.profile:  # one profiled upload to the 2-core server first (not timed)
            prof = "/tmp/bench_tiles_http_profile.json"  # (kept: its events)
            took, _, _ = _http_ingest(tmp, "prof", 2, tiles, None, o, d, v, q, b0, prof)
            time.sleep(1.0)  # (its last events written)
            print(f"profiled run (not in the medians): tiles {tiles}, 2 cores: {took:.2f} s")
            print_profile(prof)
            if not args.runs:
                return
        for r in range(args.runs):
            for k, (label, cores, t, src, rows) in enumerate(configs):
                took, got, desc = _http_ingest(tmp, f"c{k}", cores, t, src, o, d, v, q, rows)
                times[label].append(took)
                if ref is None:
                    ref = got
                else:
                    for key, want in ref.items():
                        if not np.array_equal(want, got[key], equal_nan=True):
                            np.savez("/tmp/bench_tiles_http_differ.npz",
                                     **{f"ref_{n}": x for n, x in ref.items()},
                                     **{f"got_{n}": x for n, x in got.items()})
                        assert np.array_equal(want, got[key], equal_nan=True), \
                            f"{label}: {key} differ from the first server's"
                print(f"run {r + 1}: {label}: {took:.2f} s ({desc.get('ntiles', 1)} tile(s), "
                      f"{desc.get('nsamples', '?'):,} samples; load "
                      f"{os.getloadavg()[0]:.2f})", flush=True)
    med = {k: statistics.median(x) for k, x in times.items()}
    base = med[configs[0][0]]
    print()
    for label, *_ in configs:
        print(f"{label}: median {med[label]:.2f} s (runs {', '.join(f'{x:.2f}' for x in times[label])})"
              + ("" if label == configs[0][0] else f": {base / med[label]:.2f}x the 1-core server"))
    print(f"every answer equal (bits: values; weights and sample ids inside the hull) on "
          f"{len(q.origins):,} query rays ({int(ref['inside'].sum()):,} inside)")


def run(args, tiles: int | str, cores: int, out: str, *, side: int | None = None,
        queries: int | None = None, ray: str | None = None) -> dict:
    cpus = ",".join(str(c) for c in range(cores))
    cmd = ["taskset", "-c", cpus, sys.executable, __file__, "--one", str(tiles), "--cores",
           str(cores), "--side", str(side or args.side), "--queries",
           str(queries or args.queries), "--out", out, *(["--ray-address", ray] if ray else [])]
    got = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(got.stdout.strip().splitlines()[-1])


def main() -> int:
    if sys.argv[1:2] == ["--serve-profiled"]:
        serve_profiled(sys.argv[2], sys.argv[3:])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=None,
                    help="rays: side^2 (default 1000; 548 with --http)")
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
    ap.add_argument("--http", action="store_true",
                    help="only the upload over HTTP: 1-core unsplit against 2-core tiled servers")
    ap.add_argument("--batch", type=int, nargs="+", default=[50_000],
                    help="--http: rows per upload (several: each a 2-core configuration)")
    ap.add_argument("--http-tiles", type=lambda s: s if s == "auto" else int(s), default=2,
                    help="--http: the 2-core server's field's tiles (2 or auto)")
    ap.add_argument("--old", help="--http: also the 2-core server from this checkout")
    ap.add_argument("--profile", action="store_true",
                    help="--http: first one profiled upload to the 2-core server")
    ap.add_argument("--ray-address", help=argparse.SUPPRESS)
    ap.add_argument("--one", type=lambda s: s if s == "auto" else int(s), help=argparse.SUPPRESS)
    ap.add_argument("--cores", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.http:
        over_http(args)
        return 0
    args.side = args.side or 1000
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
        for c, target in (() if args.halo_only else ((2, "issue 19: >= 1.6x"),
                                                      (1, "issue 40: >= 0.95x"))):
            a, b = med[(1, c)][0], med[(2, c)][0]
            print(f"build on {c} core(s) (median of {args.runs}): unsplit {a:.1f} s, 2 tiles "
                  f"{b:.1f} s: {a / b:.2f}x ({target})")
        if not args.halo_only:  # issue 40: the cores' gain against the unsplit build on one
            a, b = med[(1, 1)][0], med[(2, 2)][0]
            print(f"build, 2 tiles on 2 cores against the unsplit on 1 core: {a:.1f} s / "
                  f"{b:.1f} s = {a / b:.2f}x (issue 40: >= 1.7x)")
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
                  f"{100 * star.sum() / own.sum():5.1f} %; sent {100 * x['sent'] / own.sum():5.1f} "
                  f"%, of which left out {100 * x['left_out'] / own.sum():5.1f} %), own points "
                  f"{own.min():,}-{own.max():,}, "
                  f"exchange rounds {x['rounds']} ({x['exchange_s']:.1f} s), re-tiled "
                  f"{x['retiled']}, peak resident {x['rss'] / 2**20:,.0f} MiB, build "
                  f"{x['build_s']:.1f} s, "
                  f"{100 * x['forwarded']:.2f} % of queries forwarded")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
