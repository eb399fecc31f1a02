"""flatserve.Triangulation against scipy and against plain C++ CGAL (issue 3).

On 100,000 points uniform in 4D and from the paper's ray set-up (Sec. 5.2,
non-round-tripping rays removed; needs flatserve.basis), and with ``--full``
1,000,000 uniform points:

* build: ours vs scipy.spatial.Delaunay vs a plain C++ program calling CGAL
  (benchmarks/cgal_build_peer.cpp, compiled here with the flags of _core);
* interpolate 250,000 random-order queries, one thread, Hilbert sort included,
  vs scipy's LinearNDInterpolator (timed on a subset when slow: said so);
  coherent scanline order; two threads vs one;
* snapshot: write, read, read vs rebuild; peak RSS per point.

Figures are medians of several runs (fewer for the big ones). Nothing is
asserted: the script prints what it measures, with the issue's targets.

usage: python benchmarks/bench_triangulation.py [--full] [--runs N] [--no-scipy]
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

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from flatserve.triangulation import Triangulation  # noqa: E402
from timing import median_time  # noqa: E402

N_QUERIES = 250_000
D = 4
CHANNELS = 3
TARGETS = {
    "build_vs_scipy": 3.0,        # scipy time / ours, at least
    "build_vs_cgal": 1.15,        # ours / plain CGAL, at most
    "random_qps": 400_000,        # one thread, sort included, 100k points
    "vs_scipy_interp": 100.0,     # ours rate / scipy rate, at least
    "scanline_qps": 1_500_000,
    "two_threads": 1.7,
    "snapshot_read": 10.0,        # rebuild time / read time, at least (1M)
    "kb_per_point": 3.5,          # at most, 4D
}


# ------------------------------------------------------------------ helpers
def row(label, peer_label, peer, ours, unit="s", ratio=None, target=None, note=""):
    def fmt(x):
        if x is None:
            return "-"
        if unit == "s":
            return f"{x:9.3f} s"
        if unit == "/s":
            return f"{x / 1e3:8.1f}k/s" if x >= 1000 else f"{x:9.1f}/s"
        if unit == "KB":
            return f"{x:7.2f} KB"
        return f"{x:9.3g} {unit}"

    r = "" if ratio is None else f"{ratio:7.2f}x"
    t = "" if target is None else f"(target {target})"
    print(f"  {label:<38} {peer_label:<22} {fmt(peer):>12}   ours {fmt(ours):>12}  {r:>9} {t} {note}")


def compile_peer(workdir: Path) -> Path | None:
    """Compile cgal_build_peer.cpp with _core's flags (see native/CMakeLists.txt)."""
    exe = workdir / "cgal_build_peer"
    flags = ["-O3", "-DNDEBUG", "-DCGAL_NDEBUG", "-DCGAL_EIGEN3_ENABLED", "-DCGAL_USE_GMPXX=1",
             "-DBOOST_ALL_NO_LIB", "-frounding-math", "-fno-stack-protector",
             "-ffunction-sections", "-fdata-sections", "-std=gnu++17"]
    ninja = sorted(ROOT.glob("build/*/build.ninja"))
    if ninja:  # take the exact FLAGS/DEFINES of a triangulation object when built
        text = ninja[0].read_text().splitlines()
        for i, line in enumerate(text):
            if line.startswith("build CMakeFiles/_core.dir/triangulation_dim4.cpp.o"):
                got = {}
                for l2 in text[i + 1:i + 8]:
                    k, _, v = l2.strip().partition(" = ")
                    got[k] = v
                if "FLAGS" in got and "DEFINES" in got:
                    flags = (got["DEFINES"].split() + [f for f in got["FLAGS"].split()
                                                       if f not in ("-fPIC", "-fvisibility=hidden")])
                    flags = [f for f in flags if f != "-D_core_EXPORTS"]
                break
    cmd = (["g++"] + flags + ["-DPEER_DIM=4", "-I/usr/include/eigen3", str(HERE / "cgal_build_peer.cpp"),
                              "-o", str(exe), "-lgmp", "-lmpfr", "-lpthread"])
    print("  compiling peer:", " ".join(cmd[1:len(flags) + 1]))
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        print("  peer compilation failed:", getattr(exc, "stderr", exc))
        return None
    return exe


def run_peer(exe: Path, pts_file: Path, runs: int):
    out = subprocess.run([str(exe), str(pts_file), str(runs)], check=True, capture_output=True,
                         text=True).stdout.split("\n")
    ts = [float(line.split()[1]) for line in out if line.startswith("seconds")]
    rss = [int(line.split()[1]) for line in out if line.startswith("peak_rss_kb")]
    return float(np.median(ts)), rss[0] if rss else None


_CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, sys.argv[2])
from flatserve.triangulation import Triangulation
def hwm():  # this process image's peak RSS in KB (ru_maxrss inherits the parent's)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
P = np.load(sys.argv[1])
before = hwm()
t = Triangulation(P.shape[1])
t0 = time.perf_counter()
t.insert(P)
dt = time.perf_counter() - t0
after = hwm()
print(json.dumps({"seconds": dt, "peak_kb": after, "delta_kb": after - before,
                  "cells": t.nsimplex}))
"""


def build_in_child(npy: Path):
    out = subprocess.run([sys.executable, "-c", _CHILD, str(npy), str(ROOT)], check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


# ------------------------------------------------------------------ data
def uniform_points(n, seed):
    return np.random.default_rng(seed).random((n, D))


def ray_points(n, seed):
    """Embedded coordinates of rays of the paper's set-up that round-trip."""
    from flatserve.basis import Basis
    from flatserve.coordinates import OK
    from flatserve.embedding import embed

    B = Basis.around_axis(axis=2, scale=0.01)
    rng = np.random.default_rng(seed)
    out, have = [], 0
    while have < n:
        k = int((n - have) * 1.1) + 1000
        screen = np.c_[rng.uniform(-1, 1, (k, 2)), np.zeros(k)]
        eye = np.c_[rng.uniform(-1, 1, (k, 2)), rng.uniform(-4.5, -1.5, k)]
        c = B.coordinates_rays(eye, screen - eye)
        x = embed(c.weights[c.status == OK])
        out.append(x)
        have += len(x)
    return np.concatenate(out)[:n]


def scanline_queries(P, n):
    """An image-like raster: a 2D grid on a plane through the data, row by row."""
    side = int(np.sqrt(n))
    lo, hi = np.percentile(P, 5, axis=0), np.percentile(P, 95, axis=0)
    c = (lo + hi) / 2
    e1 = np.zeros(D); e1[0] = 1; e1[2] = 0.3  # noqa: E702
    e2 = np.zeros(D); e2[1] = 1; e2[3] = -0.2  # noqa: E702
    u = np.linspace(-0.5, 0.5, side)
    U, V = np.meshgrid(u, u)
    span = (hi - lo)
    Q = c + (U.reshape(-1, 1) * e1 + V.reshape(-1, 1) * e2) * span
    return np.ascontiguousarray(Q)


# ------------------------------------------------------------------ one dataset
def bench_dataset(name, P, args, tmp: Path, peer_exe, big=False):
    n = len(P)
    runs = 1 if big else args.runs
    rng = np.random.default_rng(1)
    V = rng.random((n, CHANNELS))
    print(f"\n== {name}: {n:,} points in {D}D ==")
    npy = tmp / f"{name}.npy"
    np.save(npy, P)
    binf = tmp / f"{name}.bin"
    with open(binf, "wb") as f:
        f.write(np.array([n, D], dtype=np.int64).tobytes())
        f.write(np.ascontiguousarray(P, dtype=np.float64).tobytes())

    # --- build: fresh processes (also give the peak RSS), plus the one kept here
    child = [build_in_child(npy) for _ in range(max(1, runs - 1))]
    t0 = time.perf_counter()
    tri = Triangulation(D)
    tri.insert(P, V)
    t_main = time.perf_counter() - t0
    t_ours = float(np.median([c["seconds"] for c in child] + [t_main]))
    kb_pt = float(np.median([c["delta_kb"] for c in child])) / n
    peak_mb = max(c["peak_kb"] for c in child) / 1024
    t_peer = peer_rss = None
    if peer_exe:
        t_peer, peer_rss = run_peer(peer_exe, binf, runs)
    t_scipy = None
    if not args.no_scipy and (not big or args.scipy_full):
        from scipy.spatial import Delaunay
        t_scipy, sp_tri = median_time(lambda: Delaunay(P), 1)
    else:
        sp_tri = None
    print(f"  build ({runs} run{'s' if runs > 1 else ''}, median; {tri.nsimplex:,} cells, "
          f"{tri.nsimplex / n:.1f} per vertex)")
    row("build", "scipy Delaunay", t_scipy, t_ours,
        ratio=None if t_scipy is None else t_scipy / t_ours, target=f">= {TARGETS['build_vs_scipy']}",
        note="" if t_scipy is not None else "(scipy skipped: docs/design.md: 258 s, 11.6 GB at 1M)"
        if big else "(scipy skipped)")
    if t_peer is not None:
        row("build", "plain C++ CGAL", t_peer, t_ours, ratio=t_ours / t_peer,
            target=f"<= {TARGETS['build_vs_cgal']} (ours/peer)")
    row("memory: peak RSS growth per point", "plain C++ (peak)",
        None if peer_rss is None else (peer_rss - P.nbytes / 1024) / n, kb_pt, unit="KB",
        target=f"<= {TARGETS['kb_per_point']} KB", note=f"(peak RSS of the build process {peak_mb:.0f} MB)")

    # --- queries
    q = rng.random((N_QUERIES, D)) * (P.max(0) - P.min(0)) + P.min(0)
    if name.startswith("rays"):
        q = ray_points(N_QUERIES, seed=99)
    qr = 3 if not big else 2
    tri.interpolate(q[:1000], threads=1)  # warm
    t1, (vals, inside) = median_time(lambda: tri.interpolate(q, threads=1), qr)
    rate1 = N_QUERIES / t1
    print(f"  interpolate {N_QUERIES:,} random-order queries ({inside.mean():.1%} inside), "
          f"C={CHANNELS}, median of {qr}")
    sp_rate, note = None, ""
    if sp_tri is not None or (not args.no_scipy and not big):
        from scipy.interpolate import LinearNDInterpolator
        from scipy.spatial import Delaunay
        if sp_tri is None:
            sp_tri = Delaunay(P)
        interp = LinearNDInterpolator(sp_tri, V)
        sub = args.scipy_queries
        t_sp, ref = median_time(lambda: interp(q[:sub]), 1)
        sp_rate = sub / t_sp
        note = f"(scipy on the first {sub:,} queries, its triangulation prebuilt)"
        ok = inside[:sub] & ~np.isnan(ref).any(1)
        dif = np.abs(vals[:sub][ok] - ref[ok]).max(axis=1) if ok.any() else np.zeros(0)
        note += f"; max |ours - scipy| = {dif.max(initial=0):.1e}"
        if (dif > 1e-9).any():
            # Qhull is not exact: on this data its triangulation differs from
            # CGAL's (exact predicates) in places. Check ours is self-consistent.
            loc = tri.locate(q[:sub], threads=1)
            ins = loc.inside
            recon = np.einsum("qk,qkd->qd", loc.weights[ins], P[loc.ids[ins]])
            err = np.abs(recon - q[:sub][ins]).max() / max(1.0, np.abs(q[:sub]).max())
            note += (f", {int((dif > 1e-9).sum())} queries differ > 1e-9 (scipy's Qhull is inexact; "
                     f"ours: min weight {loc.weights[ins].min():.1e}, rel. reconstruction error {err:.1e})")
    row("interpolate, 1 thread, hilbert", "scipy LinearNDInterp", sp_rate, rate1, unit="/s",
        ratio=None if sp_rate is None else rate1 / sp_rate,
        target=f">= {TARGETS['vs_scipy_interp']}x, >= {TARGETS['random_qps'] // 1000}k/s", note=note)
    t_given, _ = median_time(lambda: tri.interpolate(q[:20000], threads=1, order="given"), 1)
    row("  same queries, order='given' (no sort)", "", None, 20000 / t_given, unit="/s",
        note="(first 20,000; shows what the Hilbert sort buys)")
    sq = scanline_queries(P, N_QUERIES)
    ts, _ = median_time(lambda: tri.interpolate(sq, threads=1, order="given"), qr)
    row(f"scanlines ({len(sq):,}), 1 thread, given", "", None, len(sq) / ts, unit="/s",
        target=f">= {TARGETS['scanline_qps'] / 1e6}M/s")
    c0 = time.process_time()
    t2, (vals2, _) = median_time(lambda: tri.interpolate(q, threads=2), qr)
    cpu = (time.process_time() - c0) / qr
    same = np.array_equal(vals2, vals, equal_nan=True)
    row("interpolate, 2 threads vs 1", "1 thread", rate1, N_QUERIES / t2, unit="/s", ratio=t1 / t2,
        target=f">= {TARGETS['two_threads']}",
        note=f"(identical results: {same}; cpu/wall {cpu / t2:.2f}: below ~1.9 the 2nd core was busy)")

    # --- snapshot
    snap = tmp / f"{name}.fstri"
    tw, _ = median_time(lambda: tri.save(snap), 1 if big else 3)
    # read as a restarting server does: the built triangulation gone (at 1M it
    # holds 2.8 GB, and a read next to it pays for the extra fresh memory)
    del tri
    gc.collect()
    tr_, back = median_time(lambda: Triangulation.load(snap), 3)
    size_mb = snap.stat().st_size / 1e6
    v3, _ = back.interpolate(q[:20000], threads=1)
    same = np.array_equal(v3, vals[:20000], equal_nan=True)
    print(f"  snapshot: {size_mb:,.0f} MB ({snap.stat().st_size / n:.0f} B/point), "
          f"write {tw:.2f} s, answers identical after read: {same}")
    row("snapshot read vs rebuild", "rebuild (build)", t_ours, tr_, ratio=t_ours / tr_,
        target=f">= {TARGETS['snapshot_read']}x (at 1M)")
    del back
    snap.unlink()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--full", action="store_true", help="also 1,000,000 uniform points")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-scipy", action="store_true")
    ap.add_argument("--scipy-full", action="store_true", help="also scipy at 1M (258 s, 11.6 GB)")
    ap.add_argument("--scipy-queries", type=int, default=1000,
                    help="queries timed for scipy's LinearNDInterpolator (it is slow)")
    ap.add_argument("--no-rays", action="store_true")
    ap.add_argument("--only-full", action="store_true", help="only the 1,000,000-point set")
    args = ap.parse_args(argv)
    print(f"flatserve triangulation benchmark; {os.cpu_count()} cores; python {sys.version.split()[0]}; "
          f"load average {os.getloadavg()[0]:.1f} (other work on the machine skews the figures)")
    tmp = Path(tempfile.mkdtemp(prefix="fs-bench-tri-"))
    try:
        peer = compile_peer(tmp) if shutil.which("g++") else None
        if not args.only_full:
            bench_dataset("uniform", uniform_points(args.n, 0), args, tmp, peer)
        if not args.no_rays and not args.only_full:
            try:
                P = ray_points(args.n, seed=0)
            except Exception as exc:  # the math helper's API may not be there
                print(f"\n== rays: skipped ({type(exc).__name__}: {exc}) ==")
            else:
                bench_dataset("rays", P, args, tmp, peer)
        if args.full or args.only_full:
            bench_dataset("uniform-1M", uniform_points(1_000_000, 0), args, tmp, peer, big=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
