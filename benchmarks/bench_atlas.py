"""Atlas fields against the single chart, one core, from the same run.

1. Coordinates with routing of 1,000,000 rays whose directions are uniform on
   the sphere (origins uniform in [-1, 1]^3), covering atlas of lines in R^3
   (16 charts around the icosahedral vertex and face axes): routing (angles to the centres) plus the
   coordinates (paper Fig. 8, native kernel) and embedding (Sec. 5) in every
   chart that holds the ray -- the query path (charts closer than
   ``trusted``) and the upload path (closer than ``reach``).  Peer: one chart
   (tangent simplex around the z-axis) on 1,000,000 rays within 45 degrees
   of its axis (what it can chart).  Target >= 1,000,000 rays/s.
2. Interpolation, random order, one thread, blending included: an
   AtlasField of ``--samples`` rays (directions uniform on the sphere) queried
   at 250,000 others; peer: a single-chart Field of as many rays within 45
   degrees of its axis, queried at rays within 45 degrees.  Target >= 250k/s.
3. Memory per sample: resident-memory growth while building each field,
   divided by its distinct samples, and the duplication factor (vertices over
   all charts / distinct samples).

Usage: ``.venv/bin/python benchmarks/bench_atlas.py [--samples 100000] [--runs 3]``
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"  # one core, set before NumPy is imported

import argparse  # noqa: E402
import gc  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from flatserve import Basis, Field, Flats  # noqa: E402
from flatserve.atlas import Atlas  # noqa: E402
from flatserve.atlas_field import AtlasField  # noqa: E402
from timing import median_time

COORD_TARGET = 1_000_000
QUERY_TARGET = 250_000


def sphere_rays(n, rng):
    o = rng.uniform(-1, 1, (n, 3))
    v = rng.standard_normal((n, 3))
    return o, v


def cone_rays(n, rng, deg=45.0):
    """Directions uniform on the cap within ``deg`` of +z (the single chart's domain)."""
    o = rng.uniform(-1, 1, (n, 3))
    z = rng.uniform(np.cos(np.radians(deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    return o, np.c_[s * np.cos(phi), s * np.sin(phi), z]


def line_fn(o, v):
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    r = o - np.einsum("ni,ni->n", a, o)[:, None] * a
    return np.c_[np.sin(1.5 * r[:, 0]) + np.cos(r[:, 1]) + a[:, 0] * a[:, 1] + 0.7 * a[:, 2] ** 2]


def rss_bytes():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def chart_all(field: AtlasField, flats: Flats, radius: float, nearest: bool = True):
    """Routing + coordinates + embedding in every chart within ``radius`` (degrees);
    ``nearest``: also find each flat's nearest chart (the upload path does, a query not)."""
    ro = field.atlas.route(flats, radius, nearest=nearest)
    for c, rows in enumerate(ro.rows):
        if rows.size:
            field.fields[c].chart(flats.take(rows), threads=1)
    return ro


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=250_000)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    atlas = Atlas.covering(1, 3)
    print(f"atlas: {atlas.ncharts} charts (icosahedral vertex and face axes), covering radius "
          f"{atlas.info['covering_radius_deg']:.2f} deg; inner {atlas.inner:g}, trusted "
          f"{atlas.trusted:g}, reach {atlas.reach:g}; scale {atlas.scales[0]:g}")

    bench_coordinates(atlas, args, rng)
    gc.collect()
    bench_fields(atlas, args, rng)


def bench_coordinates(atlas, args, rng):
    """1. Routing + coordinates + embedding of ``args.n`` rays, ours and the peer."""
    o, v = sphere_rays(args.n, rng)
    f = Flats.from_rays(o, v)
    co, cv = cone_rays(args.n, rng)
    fc = Flats.from_rays(co, cv)
    probe = AtlasField(atlas)
    single = Field(Basis.around_axis(2, scale=0.01))
    t_peer = median_time(lambda: single.chart(fc, threads=1), args.runs)[0]
    t_route = median_time(lambda: atlas.route(f, atlas.trusted, nearest=False), args.runs)[0]
    t_q = median_time(lambda: chart_all(probe, f, atlas.trusted, nearest=False), args.runs)[0]
    t_u = median_time(lambda: chart_all(probe, f, atlas.reach), args.runs)[0]
    per_q = sum(r.size for r in atlas.route(f, atlas.trusted).rows) / args.n
    per_u = sum(r.size for r in atlas.route(f, atlas.reach).rows) / args.n
    okc = single.chart(fc, threads=1).ok.mean()
    print(f"\n1. coordinates of {args.n:,} rays, one core (median of {args.runs})")
    print(f"   peer: one chart, rays within 45 deg    {args.n / t_peer / 1e6:6.2f} M rays/s "
          f"({okc:.4%} round-trip)")
    print(f"   ours: routing only (query path)        {args.n / t_route / 1e6:6.2f} M rays/s")
    print(f"   ours: query path (charts per ray {per_q:.3f})  {args.n / t_q / 1e6:6.2f} M rays/s"
          f"   ratio to peer {t_peer / t_q:.2f}   target >= {COORD_TARGET / 1e6:g}M: "
          f"{'met' if args.n / t_q >= COORD_TARGET else 'NOT met'}")
    print(f"   ours: upload path (charts per ray {per_u:.3f}) {args.n / t_u / 1e6:6.2f} M rays/s"
          f"   ratio to peer {t_peer / t_u:.2f}")


def bench_fields(atlas, args, rng):
    """2. and 3.: build both fields (memory), then query them."""
    so, sv = cone_rays(args.samples, rng)
    m0 = rss_bytes()
    t0 = time.perf_counter()
    single = Field(Basis.around_axis(2, scale=0.01))
    single.add(Flats.from_rays(so, sv), line_fn(so, sv))
    t_sb = time.perf_counter() - t0
    m_single = rss_bytes() - m0
    ao, av = sphere_rays(args.samples, rng)
    m0 = rss_bytes()
    t0 = time.perf_counter()
    af = AtlasField(atlas)
    res = af.add(Flats.from_rays(ao, av), line_fn(ao, av))
    t_ab = time.perf_counter() - t0
    m_atlas = rss_bytes() - m0
    print(f"\n3. memory, {args.samples:,} samples")
    print(f"   peer: single chart {single.nsamples:,} samples, built in {t_sb:.1f} s, "
          f"{m_single / single.nsamples:,.0f} B/sample")
    print(f"   ours: atlas {res.accepted:,} accepted ({res.rejected.size} rejected), "
          f"{af.nstored:,} vertices over {atlas.ncharts} charts, built in {t_ab:.1f} s, "
          f"{m_atlas / af.nsamples:,.0f} B/sample")
    print(f"   duplication factor {af.duplication:.3f}; memory per sample ratio "
          f"{(m_atlas / af.nsamples) / (m_single / single.nsamples):.2f} (target <= 2)")

    qo, qv = sphere_rays(args.queries, rng)
    qo *= 0.8
    qf = Flats.from_rays(qo, qv)
    pqo, pqv = cone_rays(args.queries, rng, 45.0)
    pqo *= 0.8
    pf = Flats.from_rays(pqo, pqv)
    t_sp = median_time(lambda: single.query(pf, threads=1), args.runs)[0]
    t_aq = median_time(lambda: af.query(qf, threads=1), args.runs)[0]
    qa = af.query(qf, threads=1)
    qs = single.query(pf, threads=1)
    err = np.abs(qa.values - line_fn(qo, qv))[qa.inside]
    errs = np.abs(qs.values - line_fn(pqo, pqv))[qs.inside]
    print(f"\n2. interpolation of {args.queries:,} queries, random order, one thread")
    print(f"   peer: single chart, queries within 45 deg {args.queries / t_sp / 1e3:7.0f} k/s "
          f"(inside {qs.inside.mean():.4f}, median error {np.median(errs):.4f})")
    print(f"   ours: atlas, all directions, blended      {args.queries / t_aq / 1e3:7.0f} k/s "
          f"(inside {qa.inside.mean():.4f}, median error {np.median(err):.4f})   ratio "
          f"{t_sp / t_aq:.2f}   target >= {QUERY_TARGET / 1e3:g}k: "
          f"{'met' if args.queries / t_aq >= QUERY_TARGET else 'NOT met'}")


if __name__ == "__main__":
    main()
