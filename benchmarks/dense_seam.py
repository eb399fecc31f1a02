"""Planes in R^4: the relative atlas whose charts keep a net of their outer seam (the
default: 59 charts, every sample up to 7 degrees beyond its nearest centre's angle, beyond
that only samples farther than 1 in the chart's coordinates from every sample before them)
against the two it replaced, from the same run: the seam narrowed to 9 degrees once a chart
holds 25 own samples (59 charts), and the plain relative atlas (74 charts, seam of 14 at
any size).

For each ``--samples`` count: random planes and held-out random queries with a smooth
known function (``accuracy_by_kind.py``'s, seed 1, unit 1), every atlas filled with the
same samples in one batch (the stored copies do not depend on the batches: tested), and
per atlas the copies per sample, the build time, the share of queries answered, the
median error over the 8 nearest samples' on the same queries; then the net's ratios to
the others.

    .venv/bin/python benchmarks/dense_seam.py [--samples 3000 12000] [--kind 2,4]
"""
from __future__ import annotations

import argparse

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)
from accuracy_by_kind import fill, nearest, setup

from flatserve.atlas import COVER_TRAIN_DEG, DEFAULT_UNIT, Atlas


def measure(atlas, A, c, f, Aq, cq, fq, knn):
    """Copies per sample, build seconds, share answered, median error over the
    8-NN's on the same queries."""
    fld, build, ins, err = fill(atlas, A, c, f, Aq, cq, fq)
    return fld.duplication, build, ins.mean(), np.median(err[ins]) / np.median(knn[ins])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[3000, 12000])
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--kind", default="2,4")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    k, d = map(int, args.kind.split(","))
    net = Atlas.covering(k, d, unit=DEFAULT_UNIT)  # (the seams in unit 1)
    step = Atlas.covering(k, d, relative=True, inner=net.inner, trusted=net.trusted,
                          reach=net.reach, dense_reach=9.0, dense_after=25, unit=DEFAULT_UNIT)
    plain = Atlas.covering(k, d, relative=True, train_deg=COVER_TRAIN_DEG, reach=net.reach,
                           unit=DEFAULT_UNIT)
    print(f"{k}-flats in R^{d}; net: {net.ncharts} charts, radii {net.inner:g}/{net.trusted:g}/"
          f"{net.reach:g}, beyond {net.dense_reach} a net of spacing {net.seam_spacing}; "
          f"step: {step.ncharts} charts, {step.dense_reach} after {step.dense_after} own "
          f"samples; plain: {plain.ncharts} charts, radii {plain.inner:g}/{plain.trusted:g}/"
          f"{plain.reach:g}")
    print("| samples | plain: copies, build, answered, error ÷ 8-NN | step | net | copies "
          "net/plain, net/step | error net/plain, net/step |")
    print("|---|---|---|---|---|---|")
    for n in args.samples:
        A, c, f, Aq, cq, fq = setup(k, d, n, args.queries, args.seed)
        knn = np.abs(nearest(A, c, f, Aq, cq) - fq)
        p, s, q = (measure(a, A, c, f, Aq, cq, fq, knn) for a in (plain, step, net))
        cell = "{:.2f}, {:.1f} s, {:.1%}, {:.3f}".format
        print(f"| {n:,} | {cell(*p)} | {cell(*s)} | {cell(*q)} | {q[0] / p[0]:.2f}, "
              f"{q[0] / s[0]:.2f} | {q[3] / p[3]:.2f}, {q[3] / s[3]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
