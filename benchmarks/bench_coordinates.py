"""Coordinates + round-trip residual of 1,000,000 rays (paper Sec. 5.2 set-up), one core.

Set-up: screen points uniform in [-1, 1]^2 x {0}, eyes uniform in
[-1, 1]^2 x [-4.5, -1.5], basis = tangent simplex around the z-axis, scale 0.01.
Target: >= 1,000,000 lines/s on one core.  Prints ours (the batched fast path
``coordinates_rays``), the NumPy batched reference, a straightforward per-flat
Python loop of the same math (timed on a subset and extrapolated), the ratios,
and the share of rays that fail the round trip for both tangent-simplex
variants.  Figures are medians of several runs.

Usage: ``.venv/bin/python benchmarks/bench_coordinates.py [--n 1000000] [--runs 5]``
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"  # one core, set before NumPy is imported

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from flatserve.basis import Basis  # noqa: E402
from flatserve.coordinates import OK, ROUNDTRIP_TOL, _fast_rays, coordinates_rays  # noqa: E402
from flatserve.flats import PINV_RCOND  # noqa: E402
from timing import median_time

TARGET = 1_000_000  # lines per second


def rays(n, seed=0):
    rng = np.random.default_rng(seed)
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    eye = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-4.5, -1.5, n)]
    return eye, screen - eye


def loop_coordinates(Qb, rb, origins, directions):
    """The same math, one flat at a time (Fig. 8 + Sec. 2.3), plain NumPy per ray."""
    m = len(Qb)
    out = np.empty((len(origins), m))
    res = np.empty(len(origins))
    I = np.eye(3)
    e = np.zeros(5)
    e[-1] = 1.0
    for t in range(len(origins)):
        a = directions[t] / np.linalg.norm(directions[t])
        Q = I - np.outer(a, a)
        r = Q @ origins[t]
        _, V = np.linalg.eigh(Q)
        A, N = V[:, :1], V[:, 1:]
        M = np.ones((5, m))
        for l in range(m):
            M[0:2, l] = N.T @ Qb[l] @ A[:, 0]
            M[2:4, l] = N.T @ (Qb[l] @ r - rb[l])
        w = np.linalg.solve(M, e)
        Qs = np.tensordot(w, Qb, 1)
        rs = w @ rb
        lam, V = np.linalg.eigh(Qs)
        Nn = V[:, 1:]
        keep = np.abs(lam[1:]) > PINV_RCOND * np.abs(lam).max()
        rt = Nn @ np.where(keep, (Nn.T @ rs) / np.where(keep, lam[1:], 1), 0)
        res[t] = max(np.linalg.norm(Nn @ Nn.T - Q), np.linalg.norm(rt - r))
        out[t] = w
    return out, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--loop-n", type=int, default=5_000, help="subset for the per-flat loop")
    ap.add_argument("--ref-n", type=int, default=100_000, help="subset for the NumPy reference")
    args = ap.parse_args(argv)

    origins, directions = rays(args.n)
    B = Basis.around_axis(axis=2, scale=0.01)  # default variant
    native = _fast_rays() is not None
    print(f"coordinates + round-trip residual, {args.n:,} rays, paper Sec. 5.2 set-up, "
          f"basis {B.variant!r} around z, scale 0.01, one thread")
    print(f"fast path: {'native C++ (native/coordinates.hpp)' if native else 'NumPy (no native)'}")

    t_fast, c = median_time(lambda: coordinates_rays(B.Q, B.r, origins, directions, threads=1), args.runs)
    ours = args.n / t_fast

    nr = min(args.ref_n, args.n)
    t_ref, ref = median_time(lambda: coordinates_rays(B.Q, B.r, origins[:nr], directions[:nr],
                                                native=False), max(1, args.runs // 2))
    ref_rate = nr / t_ref

    nl = min(args.loop_n, args.n)
    t_loop, (wl, resl) = median_time(lambda: loop_coordinates(B.Q, B.r, origins[:nl], directions[:nl]),
                               3)
    loop_rate = nl / t_loop

    ok = ref.status == OK
    def rel(a, b):  # weights grow like 1/scale toward the chart's edge: compare relatively
        return float((np.abs(a - b).max(axis=1) / np.maximum(1.0, np.abs(b).max(axis=1))).max())

    dev = rel(c.weights[:nr][ok], ref.weights[ok])
    okl = resl <= ROUNDTRIP_TOL
    devl = rel(c.weights[:nl][okl], wl[okl])

    print()
    print(f"{'implementation':<44} {'lines/s':>14} {'ours / it':>10}")
    print(f"{'per-flat Python loop (' + format(nl, ',') + ' rays, extrapolated)':<44} "
          f"{loop_rate:>14,.0f} {ours / loop_rate:>10.1f}")
    print(f"{'NumPy batched reference (' + format(nr, ',') + ' rays)':<44} "
          f"{ref_rate:>14,.0f} {ours / ref_rate:>10.1f}")
    print(f"{'ours (coordinates_rays, ' + format(args.n, ',') + ' rays)':<44} "
          f"{ours:>14,.0f} {1.0:>10.1f}")
    print(f"target >= {TARGET:,} lines/s on one core: {'MET' if ours >= TARGET else 'NOT MET'}")
    print(f"max |w_ours - w_ref| / max(1, |w_ref|) over round-tripping rays: {dev:.2e} "
          f"(NumPy reference), {devl:.2e} (loop); "
          f"status agreement: {np.mean(c.status[:nr] == ref.status):.6f}")

    print()
    print("share of rays failing the round trip (status != OK), scale 0.01:")
    cos = np.abs(directions[:, 2]) / np.linalg.norm(directions, axis=1)
    for variant in ("paper", "tangent"):
        Bv = Basis.around_axis(axis=2, scale=0.01, variant=variant)
        cv = coordinates_rays(Bv.Q, Bv.r, origins, directions)
        fail = cv.status != OK
        print(f"  variant {variant!r:<10} {fail.mean():8.3%}   ({int(fail.sum()):,} of {args.n:,})"
              + ("   Eq. 14 as printed (+ a a^T)" if variant == "paper" else
                 "   true tangent of I - a a^T"))
    print(f"  rays steeper than 45 degrees: {np.mean(cos < np.sqrt(0.5)):8.3%}")
    return 0 if ours >= TARGET else 1


if __name__ == "__main__":
    raise SystemExit(main())
