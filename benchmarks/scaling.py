"""Per-sample costs of one field, the inputs of docs/scaling.md: memory of a
replica, snapshot size, restore time (snapshot read; replay of the log), log size
(SQLite blob, PostgreSQL table), and a snapshot's trip through PostgreSQL.

Each size runs in a fresh interpreter (its resident memory is the field's), on
the paper's ray set-up with RGB values (3 channels), inserted in 10k-ray batches
as uploads would be. PostgreSQL: a throwaway cluster (fsync on).

    python benchmarks/scaling.py [--sizes 100000 200000] [--no-postgres]
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import timing  # noqa: F401  (first: the repository root on sys.path, for tests.harness)

BATCH = 10_000
CHANNELS = 3


def rss() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def paper_rays(rng, n):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def one(n: int, pg_url: str | None) -> dict:
    from flatserve import Basis, Field
    from flatserve.service.log.blobs import pack_arrays

    rng = np.random.default_rng(n)
    basis = Basis.around_axis(axis=2, scale=0.01)
    batches = []
    for i in range(0, n, BATCH):
        o, d = paper_rays(rng, min(BATCH, n - i))
        batches.append((o, d, rng.uniform(size=(len(o), CHANNELS))))
    blob_bytes = sum(len(pack_arrays({"origins": o, "directions": d, "values": v}))
                     for o, d, v in batches)
    gc.collect()
    base = rss()
    field = Field(basis, channels=CHANNELS)
    t0 = time.perf_counter()
    for o, d, v in batches:
        field.add_rays(o, d, v)
    t_insert = time.perf_counter() - t0
    gc.collect()
    field_rss = rss() - base
    out = {"n": n, "accepted": field.nsamples, "cells": field.nsimplex, "blob_bytes": blob_bytes,
           "insert_s": t_insert, "field_rss": field_rss}
    with tempfile.TemporaryDirectory(prefix="scaling-") as tmp:
        path = Path(tmp) / "f.snap"
        t0 = time.perf_counter()
        field.save(path)
        out["save_s"] = time.perf_counter() - t0
        out["snapshot_bytes"] = path.stat().st_size
        del field
        gc.collect()
        t0 = time.perf_counter()
        Field.load(path)
        out["load_s"] = time.perf_counter() - t0
        if pg_url:
            out.update(through_postgres(pg_url, path, batches, n))
    return out


def through_postgres(url: str, snap: Path, batches, n: int) -> dict:
    """The field's batches and its snapshot stored in PostgreSQL, and read back."""
    import psycopg

    from flatserve.field import Field
    from flatserve.service.log.blobs import content_hash, pack_arrays
    from flatserve.service.log.pgstorage import PostgresBackend

    be = PostgresBackend(url)
    be.check()
    try:
        fid, _ = be.create_field(f"n{n}", {}, {"Q": np.zeros((5, 3, 3)), "r": np.zeros((5, 3))})
        t0 = time.perf_counter()
        seq = pos = 0
        for o, d, v in batches:
            arrays = {"origins": o, "directions": d, "values": v}
            seq, pos = be.add_batch(fid, idem_key=None, chash=content_hash("rays", arrays),
                                    form="rays", nrows=len(o), blob=pack_arrays(arrays))
        t_log = time.perf_counter() - t0
        t0 = time.perf_counter()
        be.write_snapshot(fid, seq, pos, lambda p, _: shutil.copyfile(snap, p) and None)
        t_put = time.perf_counter() - t0
        row = be.field(fid)
        t0 = time.perf_counter()
        be.load_snapshot(row, lambda p, _: p.stat().st_size)
        t_get = time.perf_counter() - t0
        t0 = time.perf_counter()
        be.load_snapshot(row, lambda p, _: Field.load(p))
        t_restore = time.perf_counter() - t0
        with psycopg.connect(url) as c:
            log_bytes = c.execute("SELECT pg_total_relation_size('flatserve.batches')").fetchone()[0]
            snap_bytes = c.execute(
                "SELECT pg_total_relation_size('flatserve.snapshot_chunks')").fetchone()[0]
        be.delete_field(fid)
    finally:
        be.close()
    return {"pg_log_s": t_log, "pg_log_bytes": log_bytes, "pg_snapshot_put_s": t_put,
            "pg_snapshot_get_s": t_get, "pg_restore_s": t_restore, "pg_snapshot_bytes": snap_bytes}


def kd_tiles(points: np.ndarray, ntiles: int) -> np.ndarray:
    """Tile number of each point: recursive median cuts along the widest axis
    (tiles of equal counts, as a k-d tree over the chart's coordinates)."""
    tile = np.zeros(len(points), dtype=np.int64)
    parts = [np.arange(len(points))]
    while len(parts) < ntiles:
        parts.sort(key=len)
        rows = parts.pop()
        p = points[rows]
        axis = int(np.argmax(p.max(0) - p.min(0)))
        order = rows[np.argsort(p[:, axis], kind="stable")]
        parts += [order[:len(order) // 2], order[len(order) // 2:]]
    for t, rows in enumerate(parts):
        tile[rows] = t
    return tile


def tiles(n: int, counts: list[int]) -> list[dict]:
    """What a tile of one chart must hold (Tile & Merge's converged state): its own
    samples plus the *halo*, the other tiles' vertices of the Delaunay cells that
    have a local vertex (the stars of its local vertices); and how often a query
    falls in a cell without a vertex of the tile it lies in (one forward hop)."""
    from flatserve import Basis, Field

    rng = np.random.default_rng(n + 1)
    field = Field(Basis.around_axis(axis=2, scale=0.01), channels=1)
    for i in range(0, n, BATCH):
        o, d = paper_rays(rng, min(BATCH, n - i))
        field.add_rays(o, d, rng.uniform(size=len(o)))
    pts = field.points
    cells = field.triangulation.simplices  # (ncells, 5) vertex ids
    qo, qd = paper_rays(rng, 20_000)
    chart = field.chart(__import__("flatserve").Flats.from_rays(qo, qd))
    qpts = chart.points
    qcell = field.triangulation.find_simplex(qpts)
    found = qcell >= 0
    out = []
    for T in counts:
        tile = kd_tiles(pts, T)
        halo = []
        ct = tile[cells]  # (ncells, 5) tile of each vertex
        for t in range(T):
            has = (ct == t).any(axis=1)
            verts = np.unique(cells[has])
            halo.append(int((tile[verts] != t).sum()) / max(1, int((tile == t).sum())))
        # a router knows the tiles' boxes, not the cells: the query goes to the
        # tile whose box holds its chart point, which answers if the cell it finds
        # has a vertex of its own (then the cell is in that vertex's star: global)
        qt = route(pts, tile, qpts[found])
        owner_has = (ct[qcell[found]] == qt[:, None]).any(axis=1)
        out.append({"tiles": T, "samples": int(len(pts)), "halo_mean": float(np.mean(halo)),
                    "halo_max": float(np.max(halo)),
                    "forward_hop": float(1 - owner_has.mean())})
    return out


def route(points: np.ndarray, tile: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The tile of each query point: the tile whose box (of its own samples) holds
    it, nearest box when several or none do."""
    T = int(tile.max()) + 1
    lo = np.stack([points[tile == t].min(0) for t in range(T)])
    hi = np.stack([points[tile == t].max(0) for t in range(T)])
    gap = np.maximum(0, np.maximum(lo[None] - q[:, None], q[:, None] - hi[None]))  # (q, T, dim)
    return np.argmin((gap ** 2).sum(-1), axis=1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 200_000])
    ap.add_argument("--no-postgres", action="store_true")
    ap.add_argument("--tiles", type=int, nargs="*", default=[2, 4, 8, 16],
                    help="tile counts for the halo measurement (on the first size)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--url", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.url)))
        return 0

    from contextlib import nullcontext

    from tests.harness.pgcluster import PgCluster

    rows = []
    with (nullcontext() if args.no_postgres else PgCluster(fsync=True)) as pg:
        for n in args.sizes:
            url = pg.create_database(f"scaling_{n}") if pg else None
            cmd = [sys.executable, __file__, "--one", str(n)] + (["--url", url] if url else [])
            p = subprocess.run(cmd, capture_output=True, text=True, env=os.environ)
            if p.returncode:
                print(p.stdout, p.stderr, file=sys.stderr)
                return 1
            rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(json.dumps(r))
    print("\nper accepted sample (3 channels):")
    print(f"{'samples':>9} {'RSS B':>7} {'snap B':>7} {'blob B':>7} {'insert s/100k':>14} "
          f"{'load s/100k':>12} {'save s/100k':>12} {'PG log B':>9} {'PG restore s/100k':>18}")
    for r in rows:
        a = r["accepted"]
        per = 1e5 / a
        pg_cols = (f"{r['pg_log_bytes'] / a:9.0f} {r['pg_restore_s'] * per:18.2f}"
                   if "pg_log_bytes" in r else "")
        print(f"{a:9d} {r['field_rss'] / a:7.0f} {r['snapshot_bytes'] / a:7.0f} "
              f"{r['blob_bytes'] / r['n']:7.0f} {r['insert_s'] * per:14.2f} "
              f"{r['load_s'] * per:12.3f} {r['save_s'] * per:12.3f} {pg_cols}")
    if args.tiles:
        print(f"\none chart split into k-d tiles of equal counts ({args.sizes[0]} rays): the "
              "halo a tile holds beyond its own samples (stars of its vertices), and the "
              "share of queries whose cell has no vertex in the tile they fall in")
        for r in tiles(args.sizes[0], args.tiles):
            print(f"  {r['tiles']:3d} tiles of {r['samples'] // r['tiles']:7d}: halo mean "
                  f"{r['halo_mean']:6.1%}, max {r['halo_max']:6.1%}; forward hop "
                  f"{r['forward_hop']:6.2%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
