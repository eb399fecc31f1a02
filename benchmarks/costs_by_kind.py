"""What a field of each kind (k-flats in R^d) costs: the table of docs/costs.md.

For each (k, d): the default field (``new_field`` with ``Atlas.covering(k, d)``;
points: one chart, scipy's peer) filled with ``--samples`` random flats (Haar
orientations, offsets uniform in [-1, 1]^d), then measured on it:

* charts and copies per sample (``duplication``: charts a sample is stored in),
* cells per sample (``nsimplex / nsamples``) and per stored vertex,
* memory per sample: the resident memory the field added
  (``/proc/self/statm``, in a fresh process per kind) divided by its samples,
* snapshot bytes per sample (``to_bytes``),
* insert time per 1,000 samples,
* the ceilings they imply: samples per field under the default
  ``max_simplices`` (50M cells) and in 24 GB of memory.

Each kind runs in a child process (its memory is its own).

    .venv/bin/python benchmarks/costs_by_kind.py [--samples 3000] [--kinds 1,3 2,4]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

#: The kinds of the table: (k, d).
KINDS = [(0, 2), (0, 3), (1, 2), (1, 3), (2, 3), (1, 4), (2, 4), (3, 4)]
MAX_SIMPLICES = 50_000_000
MEMORY = 24 * 2**30


def _rss() -> int:
    """Resident bytes, after giving freed memory back (so that temporaries freed
    since the last reading do not count against what stays)."""
    import ctypes
    import gc
    import os

    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def measure(k: int, d: int, n: int, seed: int = 0) -> dict:
    import numpy as np

    from flatserve import Flats
    from flatserve.atlas import DEFAULT_UNIT, Atlas
    from flatserve.contract import new_field
    from flatserve.grassmann import haar_frames
    from flatserve.service.rooms import specs

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    if k == 0:
        field = new_field(1, basis=specs.build_basis(None, 0, d))
    else:
        field = new_field(1, atlas=Atlas.covering(k, d, unit=DEFAULT_UNIT))  # (unit 1)
    t_create = time.perf_counter() - t0
    A = haar_frames(n, d, k, rng) if k else np.zeros((n, d, 0))
    flats = Flats.from_parametric(A, rng.uniform(-1, 1, (n, d)))
    values = rng.uniform(size=(n, 1))
    before = _rss()
    t0 = time.perf_counter()
    res = field.add(flats, values)
    t_insert = time.perf_counter() - t0
    grown = _rss() - before
    info = field.describe()
    ns = max(1, info["nsamples"])
    return {
        "k": k, "d": d, "samples": ns, "rejected": int(res.rejected.size),
        "charts": len(field.shards), "copies": info["nstored"] / ns,
        "cells_per_sample": info["nsimplex"] / ns,
        "cells_per_vertex": info["nsimplex"] / max(1, info["nstored"]),
        "bytes_per_sample": grown / ns, "snapshot_per_sample": len(field.to_bytes()) / ns,
        "insert_s_per_1000": 1000 * t_insert / ns, "create_s": t_create,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3000)
    ap.add_argument("--kinds", nargs="+", default=None, metavar="K,D")
    ap.add_argument("--child", nargs=3, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(*args.child)))
        return 0
    kinds = [tuple(int(x) for x in s.split(",")) for s in args.kinds] if args.kinds else KINDS
    print(f"{args.samples:,} random samples per kind (Haar orientations, offsets in [-1, 1]^d); "
          "the default field of each kind")
    head = (f"{'kind':>10} {'charts':>6} {'copies':>6} {'cells/sample':>12} {'cells/vertex':>12} "
            f"{'KB/sample':>9} {'snapshot KB':>11} {'s/1k ins':>8} {'max_simplices cap':>17} "
            f"{'24 GB cap':>10}")
    print(head)
    for k, d in kinds:
        out = subprocess.run([sys.executable, __file__, "--child", str(k), str(d),
                              str(args.samples)], capture_output=True, text=True)
        if out.returncode:
            print(f"({k}, {d}): failed\n{out.stderr[-2000:]}")
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        cap_cells = MAX_SIMPLICES / r["cells_per_sample"]
        cap_mem = MEMORY / max(r["bytes_per_sample"], 1.0)
        print(f"{f'k={k}, d={d}':>10} {r['charts']:>6} {r['copies']:>6.2f} "
              f"{r['cells_per_sample']:>12.1f} {r['cells_per_vertex']:>12.1f} "
              f"{r['bytes_per_sample'] / 1024:>9.2f} {r['snapshot_per_sample'] / 1024:>11.2f} "
              f"{r['insert_s_per_1000']:>8.2f} {cap_cells:>17,.0f} {cap_mem:>10,.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
