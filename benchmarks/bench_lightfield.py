"""Light-field rendering through the HTTP API vs the two-plane scipy baseline (issue 5).

A real server process (``python -m flatserve.service``) on a free loopback
port; the bunny light field (the paper's set-up, n x n samples; --full: the
paper's 1000^2 = 1M) is uploaded through the API (.npy batches). Then one
250^2 frame with 4x supersampling (250,000 rays) is rendered through
``POST /v1/fields/bunny/render``, median of several runs, with the server's
split (ray generation, coordinates, locate + interpolate, encoding) from its
``Server-Timing`` header. The peer: the classic two-plane parameterisation of
the same samples with ``scipy.interpolate.LinearNDInterpolator`` on the same
250,000 rays (build time printed separately). Quality of both against the
mesh's ground truth is printed too.

    .venv/bin/python benchmarks/bench_lightfield.py            # 300^2 samples
    .venv/bin/python benchmarks/bench_lightfield.py --full     # 1000^2 (slow build; scipy needs ~12 GB)
"""
from __future__ import annotations

import argparse
import io
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from PIL import Image

import timing  # noqa: F401  (first: the repository root on sys.path, for tests.harness)
from flatserve.client import Client
from tests.harness.process import free_port
from flatserve.lightfield import Camera
from flatserve.lightfield.baselines import TwoPlane
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import frame_from_rays, render_field, render_truth
from flatserve.lightfield.sampling import BASIS_SCALE, build_field, bunny_scene, sample_scene

TARGET_S = 0.5  # issue 5: a 250^2 x4 frame through the HTTP API in at most 0.5 s
UPLOAD_BATCH = 100_000


def parse_server_timing(header: str) -> dict[str, float]:
    out = {}
    for part in header.split(","):
        name, _, dur = part.strip().partition(";dur=")
        if dur:
            out[name] = float(dur) / 1e3
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="the paper's 1000^2 = 1M samples")
    ap.add_argument("--n", type=int, default=None, help="screen side (default 300, --full 1000)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--width", type=int, default=250)
    ap.add_argument("--no-two-plane", action="store_true", help="skip the scipy baseline")
    args = ap.parse_args(argv)
    n = args.n or (1000 if args.full else 300)

    scene = bunny_scene(1)
    samples, values = sample_scene(scene, n, seed=0)
    cam = Camera(focal=4.0, width=args.width, height=args.width, supersample=4)
    body = {"eye": cam.eye.tolist(), "focal": cam.focal, "width": cam.width, "height": cam.height,
            "supersample": cam.supersample}
    truth = render_truth(scene, cam).image

    tmp = tempfile.TemporaryDirectory(prefix="flatserve-bench-lf-")
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "flatserve.service", "--port", str(port), "--data-dir", tmp.name,
         "--log-level", "warning", "--snapshot-every", "0"], start_new_session=True)
    try:
        c = Client(f"http://127.0.0.1:{port}", timeout=3600)
        c.wait_ready(120)
        c.create_field("bunny", basis={"kind": "tangent_simplex", "scale": BASIS_SCALE})
        t0 = time.perf_counter()
        for lo in range(0, n * n, UPLOAD_BATCH):
            hi = min(n * n, lo + UPLOAD_BATCH)
            c.upload_rays("bunny", samples.origins[lo:hi], samples.directions[lo:hi], values[lo:hi])
            print(f"\ruploading {hi:,}/{n * n:,} samples", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
        info = c.describe("bunny")
        print(f"field: {info['nsamples']:,} of {n * n:,} samples ({n}^2, paper Sec. 5.2) "
              f"built through the API in {time.perf_counter() - t0:.1f} s")

        import httpx

        client = httpx.Client(timeout=600)
        url = f"http://127.0.0.1:{port}/v1/fields/bunny/render"
        client.post(url, json=body)  # warm-up
        totals, splits, decode = [], [], []
        img = None
        for _ in range(args.runs):
            t0 = time.perf_counter()
            r = client.post(url, json=body)
            r.raise_for_status()
            totals.append(time.perf_counter() - t0)
            splits.append(parse_server_timing(r.headers["server-timing"]))
            t1 = time.perf_counter()
            img = np.asarray(Image.open(io.BytesIO(r.content)), dtype=np.float64)[..., None] / 255
            decode.append(time.perf_counter() - t1)
        t_ours = statistics.median(totals)
        split = {k: statistics.median(s[k] for s in splits) for k in splits[0]}
        cov = float(r.headers["x-coverage"])
        print(f"frame {cam.width}^2 x{cam.supersample} = {cam.nrays:,} rays through the HTTP API "
              f"(median of {args.runs}): {t_ours:.3f} s (target <= {TARGET_S} s: "
              f"{'met' if t_ours <= TARGET_S else 'NOT met'})")
        print("  server split: " + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in split.items())
              + f"; client PNG decode {statistics.median(decode) * 1e3:.1f} ms; "
              f"transport + rest {max(t_ours - split.get('total', 0), 0) * 1e3:.1f} ms")
        print(f"  PSNR vs ground truth {psnr(img, truth, None):.2f} dB (8-bit PNG), coverage {cov:.1%}")

        # the same frame in-process (no HTTP), from a Field built from the same samples
        field, _ = build_field(samples.origins, samples.directions, values)
        inproc = [render_field(field, cam) for _ in range(args.runs)]
        t_in = statistics.median(f.seconds for f in inproc)
        print(f"  in-process render_field (same samples, same frame): {t_in:.3f} s; "
              "HTTP overhead {:.1f} ms".format((t_ours - t_in) * 1e3))

        if not args.no_two_plane:
            print(f"two-plane + scipy LinearNDInterpolator on the same {n * n:,} samples "
                  "(Delaunay in R^4; slow for large n) ...", file=sys.stderr)
            tp = TwoPlane(samples.origins, samples.directions, values)
            o, d = cam.rays()
            times = []
            for _ in range(max(1, args.runs // 2)):
                t0 = time.perf_counter()
                v, inside = tp(o, d)
                tp_img, tp_cov = frame_from_rays(cam, v, inside, 0.0)
                times.append(time.perf_counter() - t0)
            t_tp = statistics.median(times)
            print(f"peer: two-plane scipy, same frame: {t_tp:.3f} s (+ {tp.build_seconds:.1f} s Delaunay build); "
                  f"PSNR {psnr(tp_img, truth, tp_cov):.2f} dB on its {tp_cov.mean():.1%} coverage")
            print(f"ratio peer / ours (frame): {t_tp / t_ours:.2f}x through HTTP, "
                  f"{t_tp / t_in:.2f}x in-process")
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
