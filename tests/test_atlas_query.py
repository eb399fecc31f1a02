"""AtlasField.query against a plain reference implementation, bit for bit.

The oracle is the straightforward form of the query (the implementation the
optimised one replaced): route with the angle of every flat to every centre,
ask each chart's Field for all the rows it holds, blend with ``bump`` weights
in chart order.  The optimised path (one comparison pass in the routing, no
nearest chart for queries, fewer passes in the blending) must give the same
bits: values, inside, status and, with ``return_weights``, ids, weights and
charts, on random data that exercises every branch (rows outside the samples'
hull, ``clamp``, several channels, oriented rays, planes).
"""
from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from flatserve import Flats
from flatserve.atlas import RELATIVE_ANSWER_DEG, RELATIVE_LIMIT_DEG, Atlas
from flatserve.atlas_field import AtlasField, AtlasQueryResult
from flatserve.grassmann import bump, cos2_max_angle, haar_frames, orientation_frames
from flatserve.coordinates import NO_SAMPLES, NOT_REPRESENTABLE, OK


def reference_route(atlas: Atlas, flats: Flats, radius: float):
    """Rows and angles per chart (degrees ``radius``), one chart at a time; for a
    relative atlas, from the dense (n, c) angles: within ``radius`` of the row's
    nearest centre's angle and below the absolute limit, the nearest always."""
    if atlas.relative:
        ang = np.stack(reference_angles(atlas, flats), axis=1)
        best = ang.min(axis=1)
        limit = np.minimum(best + math.radians(radius), math.radians(RELATIVE_LIMIT_DEG))
        rows = [np.flatnonzero((ang[:, i] <= limit) | (ang.argmin(axis=1) == i))
                for i in range(atlas.ncharts)]
        return rows, [ang[r, i] for i, r in enumerate(rows)]
    F = orientation_frames(flats, normals=False if atlas.oriented else None)
    cr = math.cos(math.radians(radius))
    rows, angles = [], []
    if atlas.oriented or F.shape[2] == 1:
        dots = reference_cosines(atlas, F)
        for i in range(atlas.ncharts):
            col = dots[:, i]
            sel = np.flatnonzero(col > cr)
            rows.append(sel)
            angles.append(np.arccos(np.minimum(col[sel], 1.0)))
        return rows, angles
    for i in range(atlas.ncharts):
        c2 = cos2_max_angle(atlas.frames[i], F)
        sel = np.flatnonzero(c2 > cr * cr)
        rows.append(sel)
        angles.append(np.arccos(np.sqrt(c2[sel])))
    return rows, angles


def reference_cosines(atlas: Atlas, F: np.ndarray) -> np.ndarray:
    """(n, c) cosines of lines (rays) to the centres: each row's summed coordinate
    by coordinate in order (the routing's bits do not depend on the batch)."""
    a, C = F[:, :, 0], atlas.frames[:, :, 0]
    dots = a[:, :1] * C[:, 0]
    for j in range(1, a.shape[1]):
        dots += a[:, j:j + 1] * C[:, j]
    if not atlas.oriented:
        np.abs(dots, out=dots)
    return dots


def reference_angles(atlas: Atlas, flats: Flats) -> list:
    """Per chart, every row's angle to its centre (radians)."""
    F = orientation_frames(flats, normals=False if atlas.oriented else None)
    if atlas.oriented or F.shape[2] == 1:
        dots = reference_cosines(atlas, F)
        return [np.arccos(np.clip(dots[:, i], -1.0, 1.0)) for i in range(atlas.ncharts)]
    return [np.arccos(np.sqrt(np.clip(cos2_max_angle(atlas.frames[i], F), 0.0, 1.0)))
            for i in range(atlas.ncharts)]


def reference_query(field: AtlasField, flats: Flats, *, outside="nan", order="hilbert",
                    threads=None, return_weights=False) -> AtlasQueryResult:
    """The blend written densely: (q, c) weights and (q, c, C) values, one chart
    column added at a time in chart order (rows a chart does not hold add
    +0.0, which leaves every sum's bits as they are)."""
    at = field.atlas
    rows_all, angles = reference_route(at, flats, at.trusted)
    n, C, c = flats.n, field.channels, at.ncharts
    inner, trusted = math.radians(at.inner), math.radians(at.trusted)
    weights = [bump(a, inner, trusted) for a in angles]
    if at.relative:  # of the angle beyond the nearest centre's, tapered to 0 at 40 degrees
        best = np.stack(reference_angles(at, flats), axis=1).min(axis=1)
        top = math.radians(RELATIVE_ANSWER_DEG)
        weights = [bump(a - best[r], inner, trusted) * bump(a, top - math.radians(4.0), top)
                   for r, a in zip(rows_all, angles)]
    asked = np.zeros((n, c), dtype=bool)  # the chart answered the row
    good = np.zeros((n, c), dtype=bool)  # ... with a finite value
    W = np.zeros((n, c))  # its blending weight where good, 0 elsewhere
    V = np.zeros((n, c, C))
    ins = np.zeros((n, c), dtype=bool)
    ok = np.zeros((n, c), dtype=bool)
    empty = np.zeros((n, c), dtype=bool)  # the chart holds the row but no simplex
    answers = {}
    for i, rows in enumerate(rows_all):
        if rows.size and field.fields[i].nsamples == 0:
            empty[rows, i] = True
        if rows.size == 0 or field.fields[i].nsamples == 0:
            continue
        res = field.fields[i].query(flats.take(rows), outside=outside, order=order,
                                    threads=threads, return_weights=return_weights)
        answers[i] = res
        fin = np.isfinite(res.values).all(axis=1)
        asked[rows, i] = True
        good[rows, i] = fin
        W[rows[fin], i] = weights[i][fin]
        V[rows[fin], i] = res.values[fin]
        ins[rows, i] = res.inside
        ok[rows, i] = res.status == OK
        empty[rows, i] = res.status == NO_SAMPLES
    num, den = np.zeros((n, C)), np.zeros(n)
    for i in range(c):
        num += W[:, i, None] * V[:, i]
        den += W[:, i]
    has = den > 0
    values = np.full((n, C), np.nan)
    values[has] = num[has] / den[has, None]
    inside = (ins & (W > 0)).any(axis=1)
    status = np.where(ok.any(axis=1), OK,
                      np.where(empty.any(axis=1), NO_SAMPLES, NOT_REPRESENTABLE)).astype(np.int8)
    if not return_weights:
        return AtlasQueryResult(values, inside, status)
    # slot of chart i in row q: how many charts before it answered q
    P = int(np.bincount(np.concatenate(rows_all), minlength=n).max(initial=0)) if n else 0
    slot = np.cumsum(asked, axis=1) - 1
    ids = np.full((n, P, field.ndim + 1), -1, dtype=np.int64)
    wts = np.zeros(ids.shape)
    charts = np.full((n, P), -1, dtype=np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = W / np.where(has, den, np.nan)[:, None]  # (q, c)
    for i, res in answers.items():
        rows = rows_all[i]
        s = slot[rows, i]
        charts[rows, s] = i
        ids[rows, s] = res.ids
        wts[rows, s] = np.where(good[rows, i, None], res.weights, 0.0) * share[rows, i, None]
    wts[~has] = np.nan
    return AtlasQueryResult(values, inside, status, ids, wts, charts)


def assert_same_bits(a: np.ndarray, b: np.ndarray):
    assert a.shape == b.shape and a.dtype == b.dtype
    if a.dtype.kind == "f":
        a, b = a.view(np.uint64), b.view(np.uint64)
    assert np.array_equal(a, b), f"{int((a != b).sum())} of {a.size} entries differ"


def assert_same_result(got: AtlasQueryResult, want: AtlasQueryResult):
    for name in ("values", "inside", "status", "ids", "weights", "charts"):
        g, w = getattr(got, name), getattr(want, name)
        assert (g is None) == (w is None), name
        if g is not None:
            assert_same_bits(np.asarray(g), np.asarray(w))


def rays(rng, n, R):
    return Flats.from_rays(rng.uniform(-R, R, (n, 3)), rng.standard_normal((n, 3)))


@pytest.fixture(scope="module")
def fields():
    """Lines (1 and 3 channels), oriented rays and planes in R^4, sparsely sampled
    so that many queries fall outside some chart's hull."""
    rng = np.random.default_rng(21)
    out = {}
    f = rays(rng, 4000, 1.0)
    o, v = f.arrays["origins"], f.arrays["directions"]
    vals = np.c_[np.sin(o[:, 0]) + v[:, 1] ** 2, o[:, 1] * v[:, 2], np.cos(o[:, 2])]
    for C in (1, 3):
        field = AtlasField(Atlas.covering(1, 3), channels=C)
        field.add(f, vals[:, :C])
        out[f"lines{C}"] = field
    field = AtlasField(Atlas.covering(1, 3, oriented=True), channels=1)
    field.add(f, vals[:, 0] + v[:, 0])
    out["rays"] = field
    A = haar_frames(2000, 4, 2, rng)
    p = Flats.from_parametric(A, rng.uniform(-1, 1, (2000, 4)))
    field = AtlasField(Atlas.covering(2, 4, relative=False), channels=1)
    field.add(p, np.sin(p.quadrics()[1][:, 0]))
    out["planes"] = field
    field = AtlasField(Atlas.covering(2, 4, relative=True), channels=1)
    field.add(p, np.sin(p.quadrics()[1][:, 0]))
    out["planes_relative"] = field
    field = AtlasField(Atlas.covering(1, 3, relative=True), channels=3)
    field.add(f, vals)
    out["lines_relative"] = field
    out["partial"] = partial_field(rng)
    return out


def near_axis(rng, n, deg):
    """Lines through [-1, 1]^3 within ``deg`` degrees of the z-axis (either sense)."""
    t = np.radians(deg) * np.sqrt(rng.uniform(size=n))
    p = rng.uniform(0, 2 * np.pi, n)
    v = np.c_[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]
    return Flats.from_rays(rng.uniform(-1, 1, (n, 3)), v * rng.choice([-1, 1], (n, 1)))


def partial_field(rng) -> AtlasField:
    """A data-driven atlas of lines within 60 degrees of the z-axis (queries beyond
    are held by no chart), its charts filled unevenly: charts that hold samples
    spanning simplices, charts with 3 samples (not spanning: D = 4), empty charts."""
    at = Atlas.for_samples(near_axis(rng, 3000, 60.0), radius=20.0, inner=10.0, trusted=20.0,
                           reach=22.0)
    field = AtlasField(at, channels=1)
    f = near_axis(rng, 1500, 10.0)  # the charts near the axis
    o = f.arrays["origins"]
    field.add(f, np.sin(o[:, 0]) + o[:, 2])
    sizes = np.asarray(field.samples_per_chart)
    empty = np.flatnonzero(sizes == 0)
    assert empty.size >= 3
    # 3 samples only in one empty chart: on its centre line, shifted
    c = empty[0]
    a, r = at.center_A[c][:, 0], at.center_r[c]
    few = Flats.from_rays(r + np.array([[0.0, 0, 0], [0.01, 0.02, 0], [0, 0.03, 0.01]]),
                          np.tile(a, (3, 1)))
    field.add(few, np.zeros(3))
    assert np.asarray(field.samples_per_chart)[c] > 0
    return field


def queries(name, rng, n):
    if name == "partial":
        return rays(rng, n, 1.0)
    if name == "planes_relative":  # (fewer charts hold a row: nearer the samples)
        return Flats.from_parametric(haar_frames(n, 4, 2, rng), rng.uniform(-1.5, 1.5, (n, 4)))
    if name == "planes":
        return Flats.from_parametric(haar_frames(n, 4, 2, rng), rng.uniform(-10, 10, (n, 4)))
    return rays(rng, n, 1.6)  # beyond the samples' [-1, 1]^3: some rows outside a chart's hull


@pytest.mark.parametrize("name", ["lines1", "lines3", "rays", "planes", "partial",
                                  "planes_relative", "lines_relative"])
@pytest.mark.parametrize("outside", ["nan", "clamp"])
@pytest.mark.parametrize("return_weights", [False, True])
def test_query_equals_the_reference_bit_for_bit(fields, name, outside, return_weights):
    field = fields[name]
    rng = np.random.default_rng(zlib.crc32(repr((name, outside, return_weights)).encode()))
    f = queries(name, rng, 3000)
    got = field.query(f, outside=outside, return_weights=return_weights)
    want = reference_query(field, f, outside=outside, return_weights=return_weights)
    assert_same_result(got, want)
    # the data exercise the branches: rows inside and outside the hulls, rows
    # held by several charts; rows of every status
    if name == "partial":
        assert {OK, NO_SAMPLES, NOT_REPRESENTABLE} <= set(want.status.tolist())
        return
    assert 0.2 < want.inside.mean() < 0.95
    if return_weights:
        assert (want.charts[:, 1] >= 0).mean() > 0.2


def test_query_equals_the_reference_in_given_order_and_threads(fields):
    field = fields["lines1"]
    f = queries("lines1", np.random.default_rng(5), 6000)
    for threads in (1, 2, None):
        got = field.query(f, order="given", threads=threads, return_weights=True)
        want = reference_query(field, f, order="given", threads=threads, return_weights=True)
        assert_same_result(got, want)


def test_routing_equals_the_reference(fields):
    rng = np.random.default_rng(6)
    for name in ("lines1", "rays", "planes", "planes_relative", "lines_relative"):
        at = fields[name].atlas
        f = queries(name, rng, 4000)
        for radius in (at.trusted, at.reach):
            got = at.route(f, radius)
            lean = at.route(f, radius, nearest=False)
            rows, angles = reference_route(at, f, radius)
            assert lean.nearest is None and lean.nearest_angle is None
            for c in range(at.ncharts):
                for r in (got, lean):
                    assert_same_bits(r.rows[c], rows[c])
                    assert_same_bits(r.angles[c], angles[c])
            # nearest: the chart of the largest cosine, as the angles to every centre say
            assert (got.nearest == at.angles(f).argmin(axis=1)).mean() > 0.999


def test_an_empty_covering_atlas_answers_no_samples_everywhere():
    rng = np.random.default_rng(8)
    for at in (Atlas.covering(1, 3), Atlas.covering(1, 3, oriented=True)):
        field = AtlasField(at, channels=2)
        for outside in ("nan", "clamp"):
            out = field.query(rays(rng, 500, 2.0), outside=outside)
            assert (out.status == NO_SAMPLES).all()
            assert not out.inside.any() and np.isnan(out.values).all()


def test_status_says_why_a_row_has_no_value(fields):
    """Per row, from the routing and each chart's triangulation: NOT_REPRESENTABLE
    where no chart holds the query, NO_SAMPLES where the charts holding it do not
    span a simplex, OK where one does; a value only where OK."""
    field = fields["partial"]
    f = queries("partial", np.random.default_rng(9), 4000)
    out = field.query(f, outside="clamp")
    route = field.route_query(f)
    held = np.zeros(f.n, dtype=bool)
    spanned = np.zeros(f.n, dtype=bool)
    for c, rows in enumerate(route.rows):
        held[rows] = True
        if field.fields[c].nsimplex > 0:  # its samples span a simplex
            spanned[rows] = True
    assert held.any() and (~held).any() and (held & ~spanned).any() and spanned.any()
    np.testing.assert_array_equal(out.status == NOT_REPRESENTABLE, ~held)
    np.testing.assert_array_equal(out.status == NO_SAMPLES, held & ~spanned)
    np.testing.assert_array_equal(out.status == OK, spanned)
    assert np.isnan(out.values[out.status != OK]).all() and not out.inside[out.status != OK].any()
    assert np.isfinite(out.values[out.status == OK]).all()  # clamp: every OK row has a value
