"""How well a field of each kind (k-flats in R^d) interpolates: the paper's charts
against isometric charts (``flatserve.warp``) and a relative atlas, and the 8 nearest
samples as a naive peer, from the same run.

For each (k, d) of ``--kinds``: ``--samples`` random flats (Haar orientations,
offsets uniform in [-1, 1]^d; as ``costs_by_kind.py``) carrying a smooth known
function of the flat, ``f = sin(<P, W>) + cos(<c, w>)`` (``P`` the flat's
direction projector, ``c`` its point closest to the origin, ``W`` and ``w``
seeded), and ``--queries`` held-out random flats. Measured:

1. a covering atlas (``Atlas.covering(k, d)``) with balls about its centres
   (``relative=False``) and the paper's charts, the same with isometric charts
   (``isometric=True``), and with radii measured from each flat's nearest centre
   (``relative=True``, the default from R^4 on; the paper's charts): charts, copies per sample, build time,
   the share of queries answered, the median error of the answered ones, and
   the 8 nearest samples' on those same queries (inverse-distance weights in
   the chordal metric ``|P1 - P2|^2 / 2 + |c1 - c2|^2``), and the ratio; then
   the median errors on the queries the paper's and each other atlas both answer;
   with ``--fit-unit`` also the default atlas in the unit
   ``flatserve.atlas_field.fitted_unit`` chose from the samples (held out among
   them), against the 8 nearest samples as above and in the same unit (offsets
   over the unit in the chordal metric: the fair peer); with ``--gradient`` as well
   that field's answers by the gradient interpolant (``flatserve.gradient``: the
   cell's vertices' Taylor expansions blended; the same cells, weights and
   queries answered);
   and the default atlas's median error by the query's angle from its nearest
   centre (is it flat across where the charts answer?);
2. ``--one-chart``: one chart (the default centre) holding the samples within
   ``--sample-deg`` (44, as far as an atlas stores them) degrees of it, queried
   within 40 degrees, paper's against isometric, the median error by the
   query's angle from the centre (is it flat across the chart?); ``--seeds N``
   pools the errors of N functions (one function's easy and hard places fall
   in bins by chance).

    .venv/bin/python benchmarks/accuracy_by_kind.py [--kinds 2,3 1,4 2,4] [--samples 3000]
    .venv/bin/python benchmarks/accuracy_by_kind.py --fit-unit --kinds 1,3 2,3 3,4 1,4 2,4
    .venv/bin/python benchmarks/accuracy_by_kind.py --fit-unit --gradient --kinds 1,3 2,4
    .venv/bin/python benchmarks/accuracy_by_kind.py --one-chart --seeds 8 [--kinds 2,3 2,4]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import timing  # noqa: F401  (the repository root on sys.path)

from flatserve import Flats
from flatserve.atlas import DEFAULT_UNIT, Atlas
from flatserve.atlas_field import AtlasField, fitted_unit
from flatserve.basis import Basis
from flatserve.field import Field
from flatserve.grassmann import haar_frames
from flatserve.warp import FlatWarp, LineWarp

KINDS = [(2, 3), (3, 4), (1, 4), (2, 4)]
BINS = [0, 10, 20, 30, 35, 40]


def random_flats(rng, n, k, d, center=None, maxdeg=None):
    """Haar-random k-flats (frames (n, d, k), closest points (n, d)); with ``center``
    (d, k) only those within ``maxdeg`` of it."""
    As, cs = [], []
    while sum(len(a) for a in As) < n:
        A = haar_frames(4 * n if center is not None else n, d, k, rng)
        p = rng.uniform(-1, 1, (len(A), d))
        if center is not None:
            s = np.linalg.svd(np.einsum("dk,ndj->nkj", center, A), compute_uv=False)
            keep = np.degrees(np.arccos(np.clip(s.min(axis=1), -1, 1))) < maxdeg
            A, p = A[keep], p[keep]
        As.append(A)
        cs.append(p - np.einsum("ndk,nek,ne->nd", A, A, p))
    return np.concatenate(As)[:n], np.concatenate(cs)[:n]


def truth(A, c, W, w):
    P = np.einsum("ndk,nek->nde", A, A)
    return np.sin(np.einsum("nde,de->n", P, W)) + np.cos(c @ w)


def chordal(A, c):
    P = np.einsum("ndk,nek->nde", A, A).reshape(len(A), -1)
    return np.concatenate([P / np.sqrt(2.0), c], axis=1)


def nearest(A, c, f, Aq, cq, n=8):
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(chordal(A, c)).query(chordal(Aq, cq), n)
    wt = 1.0 / np.maximum(dist, 1e-12)
    return (f[idx] * wt).sum(axis=1) / wt.sum(axis=1)


def setup(k, d, n, nq, seed, center=None, maxdeg=None, sample_deg=None):
    """Samples (within ``sample_deg`` of ``center``, default ``maxdeg``) and queries
    (within ``maxdeg``) with their true values."""
    rng = np.random.default_rng(seed)
    W = rng.normal(size=(d, d))
    W, w = W + W.T, rng.normal(size=d)
    A, c = random_flats(rng, n, k, d, center, maxdeg if sample_deg is None else sample_deg)
    Aq, cq = random_flats(rng, nq, k, d, center, maxdeg)
    return A, c, truth(A, c, W, w), Aq, cq, truth(Aq, cq, W, w)


def fill(atlas, A, c, f, Aq, cq, fq):
    """A field over ``atlas`` filled with the samples in one batch, and queried:
    ``(field, build seconds, inside (q,) bool, absolute error (q,))``."""
    fld = AtlasField(atlas, 1)
    t0 = time.perf_counter()
    fld.add(Flats.from_parametric(A, c), f[:, None])
    t = time.perf_counter() - t0
    res = fld.query(Flats.from_parametric(Aq, cq))
    return fld, t, np.asarray(res.inside), np.abs(np.asarray(res.values)[:, 0] - fq)


def atlas_case(k, d, n, nq, seed, fit=False, gradient=False):
    A, c, f, Aq, cq, fq = setup(k, d, n, nq, seed)
    knn = np.abs(nearest(A, c, f, Aq, cq) - fq)
    print(f"\n{k}-flats in R^{d}: {n:,} samples, {nq:,} queries; 8 nearest samples: median "
          f"error {np.median(knn):.4f}")
    print("| charts | count | copies per sample | build | answered | median error | 8-NN on "
          "the same | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    got = {}
    default = Atlas.covering(k, d, unit=DEFAULT_UNIT)  # (the figures in docs/costs.md: unit 1)
    for name, iso, rel in (("paper", False, False), ("isometric", True, False),
                           ("relative", False, True)):
        atlas = Atlas.covering(k, d, isometric=iso, relative=rel)
        fld, t, ins, errs = fill(atlas, A, c, f, Aq, cq, fq)
        if (atlas.isometric, atlas.relative) == (default.isometric, default.relative):
            got["default"] = fld
        err = errs[ins]
        got[name] = (ins, errs)
        ratio = np.median(err) / np.median(knn[ins])
        print(f"| {name} | {atlas.ncharts} | {fld.duplication:.2f} | "
              f"{t:.1f} s | {ins.mean():.1%} | {np.median(err):.4f} | "
              f"{np.median(knn[ins]):.4f} | {ratio:.2f} |")
    if fit:  # the default atlas in a unit fitted to the samples (held out among them)
        atlas = Atlas.covering(k, d, unit=DEFAULT_UNIT)
        t0 = time.perf_counter()
        fu = fitted_unit(atlas, Flats.from_parametric(A, c), f)
        tf = time.perf_counter() - t0
        fld = AtlasField(atlas.with_unit(fu.unit), 1)
        fld.add(Flats.from_parametric(A, c), f[:, None])
        # the peer with offsets weighed alike (its chordal metric's offsets over the unit)
        fair = np.abs(nearest(A, c / fu.unit, f, Aq, cq / fu.unit) - fq)
        for interpolant in ("linear", "gradient") if gradient else ("linear",):
            t0 = time.perf_counter()
            res = fld.query(Flats.from_parametric(Aq, cq), interpolant=interpolant)
            tq = time.perf_counter() - t0
            ins = np.asarray(res.inside)
            err = np.abs(np.asarray(res.values)[:, 0] - fq)[ins]
            print(f"| fitted unit {fu.unit:.3g} (of {', '.join(f'{u:.3g}' for u in fu.candidates)}; "
                  f"{tf:.1f} s), {interpolant} (query {tq:.2f} s) | {atlas.ncharts} | "
                  f"{fld.duplication:.2f} | | {ins.mean():.1%} | "
                  f"{np.median(err):.4f} | {np.median(knn[ins]):.4f} | "
                  f"{np.median(err) / np.median(knn[ins]):.2f} (8-NN in the same unit: "
                  f"{np.median(fair[ins]):.4f}, {np.median(err) / np.median(fair[ins]):.2f}) |")
    by_angle(got.pop("default"), Aq, cq, fq, knn)
    both = got["paper"][0] & got["isometric"][0]
    only = got["paper"][0] & ~both
    print(f"on the {both.mean():.1%} of queries both answer: median error paper "
          f"{np.median(got['paper'][1][both]):.4f}, isometric "
          f"{np.median(got['isometric'][1][both]):.4f}, 8-NN {np.median(knn[both]):.4f}"
          + (f"; the paper's on the queries only it answers "
             f"{np.median(got['paper'][1][only]):.4f}" if only.any() else ""))
    both = got["paper"][0] & got["relative"][0]
    print(f"on the {both.mean():.1%} of queries the paper's and the relative atlas answer: "
          f"median error paper {np.median(got['paper'][1][both]):.4f}, relative "
          f"{np.median(got['relative'][1][both]):.4f}, 8-NN {np.median(knn[both]):.4f}")


def by_angle(fld, Aq, cq, fq, knn, width=5.0):
    """The default atlas's median error (and the 8-NN's on the same queries) by the
    query's angle from its nearest centre: is the error flat across where the
    charts answer? (``fld``: the default atlas's field, filled.)"""
    atlas = fld.atlas
    qf = Flats.from_parametric(Aq, cq)
    res = fld.query(qf)
    ins = np.asarray(res.inside)
    e = np.abs(np.asarray(res.values)[:, 0] - fq)
    ang = np.degrees(atlas.route(qf, atlas.trusted).nearest_angle)
    edges = np.arange(0.0, ang.max() + width, width)
    print(f"default atlas ({'relative' if atlas.relative else 'balls'}, "
          f"{'isometric' if atlas.isometric else 'paper'} charts): median error by the "
          "query's angle from its nearest centre (answered; 8-NN on the same)")
    print("| degrees | " + " | ".join(f"{a:g}-{b:g}" for a, b in zip(edges, edges[1:]))
          + " | last over first |")
    print("|---" * len(edges) + "|---|")
    meds, cells = [], []
    for a, b in zip(edges, edges[1:]):
        sel = ins & (ang >= a) & (ang < b)
        meds.append(np.median(e[sel]) if sel.sum() >= 10 else np.nan)
        cells.append(f"{meds[-1]:.4f} ({np.median(knn[sel]):.4f}, {sel.sum()})"
                     if sel.sum() >= 10 else f"({sel.sum()} queries)")
    ok = [m for m in meds if np.isfinite(m)]
    print("| error | " + " | ".join(cells)
          + (f" | {ok[-1] / ok[0]:.2f} |" if ok else " | (no bin of 10 answered queries) |"))


def one_chart_case(k, d, n, nq, seed, maxdeg=40.0, sample_deg=44.0, seeds=1):
    """One chart, paper's and isometric: median error by the query's angle from its
    centre, the errors of ``seeds`` functions pooled (seeds ``seed``,
    ``seed + 1``, ...: each its own ``W``, ``w``, samples and queries). One
    function alone has easy and hard places, and a bin of the chart may fall on
    either (lines in R^3, isometric, last bin over first for seeds 1-4: 1.67,
    1.10, 1.77, 1.11); pooled over functions, each bin sees the function's
    every kind of place and the ratio measures the chart."""
    Qc, rc = Basis.default_center(k, d)
    center = np.eye(d)[:, d - k:]
    basis = Basis.tangent_simplex(Qc, rc, k)
    charts = (("paper", None),
              ("isometric", (LineWarp if k == 1 else FlatWarp).calibrate(basis)))
    errs = {name: [] for name, _ in charts}
    inside = {name: [] for name, _ in charts}
    angles, ratios = [], {name: [] for name, _ in charts}
    for s in range(seed, seed + seeds):
        A, c, f, Aq, cq, fq = setup(k, d, n, nq, s, center, maxdeg, sample_deg)
        ang = np.degrees(np.arccos(np.clip(np.linalg.svd(
            np.einsum("dk,ndj->nkj", center, Aq), compute_uv=False).min(axis=1), -1, 1)))
        angles.append(ang)
        for name, warp in charts:
            fld = Field(basis, 1, warp=warp)
            fld.add(Flats.from_parametric(A, c), f[:, None])
            res = fld.query(Flats.from_parametric(Aq, cq))
            ins = np.asarray(res.inside)
            e = np.abs(np.asarray(res.values)[:, 0] - fq)
            errs[name].append(e)
            inside[name].append(ins)
            sel = [ins & (ang >= a) & (ang < b) for a, b in (BINS[:2], BINS[-2:])]
            if all(s.any() for s in sel):  # (a function with no query in a bin: no ratio)
                ratios[name].append(np.median(e[sel[1]]) / np.median(e[sel[0]]))
    ang = np.concatenate(angles)
    print(f"\none chart of {k}-flats in R^{d} (samples within {sample_deg:g} degrees of its "
          f"centre, queries within {maxdeg:g}; {seeds} function(s), seeds {seed}-"
          f"{seed + seeds - 1}, errors pooled): median error by the query's angle from the "
          "centre")
    print("| chart | answered | " + " | ".join(f"{a}-{b} deg" for a, b in zip(BINS, BINS[1:]))
          + " | last bin over first | per function: median (range) |")
    print("|---" * (len(BINS) + 3) + "|")
    for name, _ in charts:
        e, ins = np.concatenate(errs[name]), np.concatenate(inside[name])
        med = [np.median(e[ins & (ang >= a) & (ang < b)]) for a, b in zip(BINS, BINS[1:])]
        r = np.array(ratios[name])
        print(f"| {name} | {ins.mean():.1%} | " + " | ".join(f"{m:.4f}" for m in med)
              + f" | {med[-1] / med[0]:.2f} | "
              + (f"{np.median(r):.2f} ({r.min():.2f}-{r.max():.2f}, {r.size}) |" if r.size
                 else "(no function with queries in both bins) |"))
    print("| queries | | " + " | ".join(str(int(((ang >= a) & (ang < b)).sum()))
                                         for a, b in zip(BINS, BINS[1:])) + " | | |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kinds", nargs="+", default=[f"{k},{d}" for k, d in KINDS])
    ap.add_argument("--samples", type=int, default=3000)
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--one-chart", action="store_true")
    ap.add_argument("--sample-deg", type=float, default=44.0,
                    help="--one-chart: samples within this angle of the centre (default 44, "
                         "as far as an atlas stores them; queries within 40)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="--one-chart: pool the errors of this many functions (seeds from "
                         "--seed on)")
    ap.add_argument("--fit-unit", action="store_true",
                    help="also the default atlas in a unit fitted to the samples")
    ap.add_argument("--gradient", action="store_true",
                    help="--fit-unit: also that atlas's answers by the gradient interpolant")
    args = ap.parse_args()
    if args.gradient and not args.fit_unit:
        ap.error("--gradient measures the fitted-unit atlas: give --fit-unit too")
    for kd in args.kinds:
        k, d = map(int, kd.split(","))
        if args.one_chart:
            one_chart_case(k, d, args.samples, args.queries, args.seed,
                           sample_deg=args.sample_deg, seeds=args.seeds)
        else:
            atlas_case(k, d, args.samples, args.queries, args.seed, fit=args.fit_unit,
                       gradient=args.gradient)


if __name__ == "__main__":
    main()
