"""A field's shards on every core (issue 18): threads against one thread, same run.

The demo's field: rays from eyes all around the bunny (the demo's sampling,
:func:`flatserve.lightfield.sampling.orbit_samples`) in an oriented covering
atlas (``Atlas.covering(1, 3, oriented=True, unit=object_unit(0.5))``, 32
charts, the service's default). For each of one thread (the peer: the
sequential loop over the charts) and ``--threads`` threads
(:func:`flatserve.parallel.set_shard_threads`), interleaved, medians of
``--runs``:

1. ingest: chart + insert of every ray (``prepare`` and ``insert_prepared`` of
   batches of 50,000, as the service's applier does)   -> target >= 1.7x on 2 cores
2. restore: :meth:`AtlasField.from_bytes` of its snapshot -> target >= 1.7x
3. one query of ``--queries`` rays from eyes all around, each chart's
   locate on one native thread (so that the threads are the charts')
                                                         -> target >= 1.5x
4. snapshot: :meth:`AtlasField.to_bytes` (no target)
5. the bytes a snapshot in parts (:meth:`AtlasField.write_parts`, as the
   service writes them) writes after a batch of 1,000 rays in one chart,
   against the whole field's file

Every timed answer is checked equal (bits) between the two.

    .venv/bin/python benchmarks/bench_shards.py [--rays 400000] [--threads 2] [--runs 3]
"""
from __future__ import annotations

import argparse
import io
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)
from flatserve import Flats
from flatserve.atlas import Atlas, object_unit
from flatserve.atlas_field import AtlasField
from flatserve.lightfield.camera import sphere_samples
from flatserve.lightfield.sampling import bunny_scene, orbit_samples
from flatserve.parallel import set_shard_threads
from flatserve.service.server import limit_blas_threads
from tests.harness.charts import rays_in_one_chart

BATCH = 50_000


def build(origins, directions, values) -> AtlasField:
    field = AtlasField(Atlas.covering(1, 3, oriented=True, unit=object_unit(0.5)),
                       channels=values.shape[1])
    for i in range(0, len(origins), BATCH):
        f = Flats.from_rays(origins[i:i + BATCH], directions[i:i + BATCH])
        field.insert_prepared(field.prepare(f, values[i:i + BATCH]))
    return field


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=400_000, help="sample rays (default 400,000)")
    ap.add_argument("--queries", type=int, default=250_000, help="rays in the query")
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)),
                    help="shard threads against one (default: the cores)")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    limit_blas_threads(1)  # as the server does: BLAS threads only spin on thin products

    scene = bunny_scene()
    samples, values = orbit_samples(scene, args.rays, seed=0)
    o, d = samples.origins, samples.directions
    q = sphere_samples(args.queries, np.random.default_rng(1))
    qf = Flats.from_rays(q.origins, q.directions)
    print(f"{args.rays:,} rays from eyes all around the bunny, oriented covering atlas (32 charts);"
          f" {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; 1 thread vs {args.threads}")

    times: dict[str, dict[int, list[float]]] = {k: {1: [], args.threads: []}
                                                for k in ("ingest", "restore", "query", "snapshot")}
    ref = {}
    for run in range(args.runs):
        for n in (1, args.threads) if run % 2 == 0 else (args.threads, 1):
            set_shard_threads(n)
            t, field = timed(lambda: build(o, d, values))
            times["ingest"][n].append(t)
            t, blob = timed(field.to_bytes)
            times["snapshot"][n].append(t)
            field = None  # freed before the next build
            t, field = timed(lambda: AtlasField.from_bytes(blob))
            times["restore"][n].append(t)
            t, res = timed(lambda: field.query(qf, threads=1))  # each chart on one core
            times["query"][n].append(t)
            if n not in ref:
                ref[n] = (blob, res.values)
            last, field = field, None  # (the last one kept for 5.)
    (b1, v1), (bn, vn) = ref[1], ref[args.threads]
    assert b1 == bn, "the snapshots differ"
    assert np.array_equal(v1, vn, equal_nan=True), "the answers differ"
    print(f"answers and snapshots bit for bit equal; duplication "
          f"{AtlasField.from_bytes(b1).duplication:.2f}, snapshot {len(b1) / 2**20:.0f} MiB")

    # 5. the bytes a snapshot writes after a batch that touches one chart
    with tempfile.TemporaryDirectory() as tmp:
        first, second = Path(tmp, "1"), Path(tmp, "2")
        first.mkdir()
        second.mkdir()
        keys = last.write_parts(io.BytesIO(), first)
        rng = np.random.default_rng(2)
        o1, d1 = rays_in_one_chart(last, rng, 0, 1000)
        last.insert_prepared(last.prepare(Flats.from_rays(o1, d1), rng.uniform(size=(1000, 1))))
        head = io.BytesIO()
        t, keys2 = timed(lambda: last.write_parts(head, second, known=set(keys)))
        written = len(head.getvalue()) + sum(p.stat().st_size for p in second.iterdir())
        changed = sum(a != b for a, b in zip(keys, keys2))
    whole = len(last.to_bytes())
    print(f"snapshot after a batch of 1,000 rays in one chart of {last.atlas.ncharts}: whole field "
          f"{whole / 2**20:8.1f} MiB | in parts {written / 2**20:8.1f} MiB written ({changed} part "
          f"changed, {t:.3f} s) | {whole / written:5.1f}x fewer bytes")

    targets = {"ingest": 1.7, "restore": 1.7, "query": 1.5, "snapshot": None}
    for what, by in times.items():
        one, many = statistics.median(by[1]), statistics.median(by[args.threads])
        target = targets[what]
        print(f"{what:9s} 1 thread {one:8.3f} s | {args.threads} threads {many:8.3f} s | "
              f"speed-up {one / many:5.2f}x" + (f" (target >= {target}x)" if target else "")
              + f"  [median of {len(by[1])}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
