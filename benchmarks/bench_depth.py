"""A capture all around, rendered through its depth: what the depth costs (issue 37).

The sphere rig of ``flatserve lightfield capture-figure`` (62 cameras on a
sphere of radius 3 looking at ``blocks_scene``, 64 x 64 pixels each: 253,952
rays; ``--size`` scales the sides), in the library (no HTTP):

1. Depth maps (``depth.depth_map``, plane sweep against the 4 nearest
   cameras): seconds per photograph, median over the rig.
2. The field the importer creates (``rig.capture_atlas``, the colour and the
   depth channel): build seconds.
3. A held-out view (``--width`` square, supersample 1, the first held-out
   camera of the rig scaled up), medians of ``--runs``:
   ``depth.render_guided`` (ours: 49 field lookups a ray), the same field
   rendered alone (``render.render_field``: one lookup a ray), and the peer,
   the two-sphere 6 nearest rays (``baselines.TwoSphere``, radius 0.6, scipy
   cKDTree, ``workers=-1``; its tree's build printed apart). PSNR of each
   against the scene's own photograph.

A table at the end (the peer's figure, ours, the ratio) and the load average
before and after.

    .venv/bin/python benchmarks/bench_depth.py              # full size (~10 min on a busy 2-core machine)
    .venv/bin/python benchmarks/bench_depth.py --quick      # smoke run (quarter-size images, a 64 x 64 view)
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from timing import median_time
from flatserve.atlas_field import AtlasField
from flatserve.flats import Flats
from flatserve.lightfield.baselines import TwoSphere
from flatserve.lightfield.capture_figure import photograph, synthetic_rig
from flatserve.lightfield.depth import depth_map, depth_values, render_guided
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import render_field
from flatserve.lightfield.rig import capture_atlas, depth_rig
from flatserve.lightfield.sampling import blocks_scene

BATCH = 100_000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=float, default=1.0, help="image sides times this (default 1: 64 x 64)")
    ap.add_argument("--width", type=int, default=256, help="the held-out view's side (default 256)")
    ap.add_argument("--runs", type=int, default=3, help="renders and lookups per method (medians)")
    ap.add_argument("--quick", action="store_true", help="quarter-size images, a 64 x 64 view, 1 run")
    args = ap.parse_args()
    if args.quick:
        args.size, args.width, args.runs = 0.25, 64, 1
    print(f"load average before: {os.getloadavg()}")
    scene = blocks_scene()
    cams, held = synthetic_rig("sphere", size=args.size)
    rig = depth_rig(cams)
    photos = [photograph(scene, c) for c in cams]
    o = np.concatenate([c.rays()[0] for c in cams])
    d = np.concatenate([c.rays()[1] for c in cams])
    v = np.concatenate([p.reshape(-1, p.shape[2]) for p in photos])
    print(f"sphere rig: {len(cams)} cameras of {cams[0].width} x {cams[0].height}, {len(o):,} rays")

    per, depths = [], []
    for i in range(len(cams)):
        t0 = time.perf_counter()
        depths.append(depth_map(i, cams, lambda j: photos[j], center=rig.center).reshape(-1))
        per.append(time.perf_counter() - t0)
    t_depth = statistics.median(per)
    print(f"1. depth maps: {t_depth * 1e3:.1f} ms per photograph (median of {len(cams)}), "
          f"{sum(per):.1f} s in all")

    t0 = time.perf_counter()
    field = AtlasField(capture_atlas(cams), channels=2)
    values = np.c_[v, depth_values(o, d, np.concatenate(depths), rig.center)]
    for lo in range(0, len(o), BATCH):
        field.add(Flats.from_rays(o[lo:lo + BATCH], d[lo:lo + BATCH]), values[lo:lo + BATCH])
    field.settle()
    print(f"2. field (colour + depth): built in {time.perf_counter() - t0:.1f} s, "
          f"{field.atlas.ncharts} charts")

    view = held[0].scaled(args.width, args.width)
    truth = photograph(scene, view)
    t_ours, ours = median_time(lambda: render_guided(field, view, rig), args.runs)
    t_plain, plain = median_time(lambda: render_field(field, view), args.runs)
    t0 = time.perf_counter()
    peer = TwoSphere(o, d, v, radius=0.6, k=6)
    t_tree = time.perf_counter() - t0
    qo, qd = view.rays()
    t_peer, (pv, pok) = median_time(lambda: peer(qo, qd, workers=-1), args.runs)
    peer_img = view.resolve(np.where(pok[:, None], pv, 0.0))
    p_ours, p_plain, p_peer = (psnr(ours.image, truth), psnr(plain.image[..., :1], truth),
                               psnr(peer_img, truth))
    print(f"3. held-out view {view.width} x {view.height} ({view.nrays:,} rays), medians of {args.runs}:")
    print(f"   depth-guided {t_ours * 1e3:.0f} ms ({p_ours:.2f} dB); the field alone {t_plain * 1e3:.0f} ms "
          f"({p_plain:.2f} dB); two-sphere 6 nearest rays {t_peer * 1e3:.0f} ms ({p_peer:.2f} dB; "
          f"its tree built in {t_tree:.2f} s)")
    print()
    print("| measure | peer (two-sphere, cKDTree) | ours | ratio (ours / peer) |")
    print("|---|---|---|---|")
    print(f"| render ms/frame, depth-guided | {t_peer * 1e3:.0f} | {t_ours * 1e3:.0f} | {t_ours / t_peer:.1f}x |")
    print(f"| render ms/frame, the field alone | {t_peer * 1e3:.0f} | {t_plain * 1e3:.0f} | "
          f"{t_plain / t_peer:.1f}x |")
    print(f"| PSNR of the view (dB), depth-guided | {p_peer:.2f} | {p_ours:.2f} | {p_ours - p_peer:+.2f} dB |")
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
