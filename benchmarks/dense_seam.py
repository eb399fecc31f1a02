"""Planes in R^4: the relative atlas whose charts narrow their seam once dense (the
default: 59 charts, 9 degrees after 25 own samples) against the plain relative atlas
it replaced (74 charts, seam of 14 degrees at any size), from the same run.

For each ``--samples`` count: random planes and held-out random queries with a smooth
known function (``accuracy_by_kind.py``'s, seed 1, unit 1), both atlases filled with
the same samples in one batch (the stored copies do not depend on the batches: tested),
and per atlas the copies per sample, the build time, the share of queries answered, the
median error over the 8 nearest samples' on the same queries; then the ratios.

    .venv/bin/python benchmarks/dense_seam.py [--samples 3000 12000] [--kind 2,4]
"""
from __future__ import annotations

import argparse

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)
from accuracy_by_kind import fill, nearest, setup

from flatserve.atlas import COVER_TRAIN_DEG, Atlas


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
    dense = Atlas.covering(k, d)
    plain = Atlas.covering(k, d, relative=True, train_deg=COVER_TRAIN_DEG, reach=dense.reach)
    print(f"{k}-flats in R^{d}; dense seam: {dense.ncharts} charts, radii {dense.inner:g}/"
          f"{dense.trusted:g}/{dense.reach:g}, {dense.dense_reach} after {dense.dense_after} own "
          f"samples; plain: {plain.ncharts} charts, radii {plain.inner:g}/{plain.trusted:g}/"
          f"{plain.reach:g}")
    print("| samples | plain: copies, build, answered, error ÷ 8-NN | dense seam: copies, "
          "build, answered, error ÷ 8-NN | copies dense/plain | error dense/plain |")
    print("|---|---|---|---|---|")
    for n in args.samples:
        A, c, f, Aq, cq, fq = setup(k, d, n, args.queries, args.seed)
        knn = np.abs(nearest(A, c, f, Aq, cq) - fq)
        p = measure(plain, A, c, f, Aq, cq, fq, knn)
        q = measure(dense, A, c, f, Aq, cq, fq, knn)
        cell = "{:.2f}, {:.1f} s, {:.1%}, {:.3f}".format
        print(f"| {n:,} | {cell(*p)} | {cell(*q)} | {q[0] / p[0]:.2f} | {q[3] / p[3]:.2f} |",
              flush=True)


if __name__ == "__main__":
    main()
