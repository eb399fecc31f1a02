"""Atlases and atlas fields (flatserve/atlas.py, flatserve/atlas_field.py, flatserve/grassmann.py).

Oracles: principal angles against an SVD, the coordinates' own round trip,
a single-chart Field on the same samples, the blended weights recombining the
sample values, a smooth function sampled densely.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from flatserve import Flats
from flatserve.atlas import (COVER_MARGIN_DEG, COVER_RADII_3D, DEFAULT_UNIT, Atlas, data_unit,
                             object_unit)
from flatserve.atlas_field import AtlasField
from flatserve.grassmann import (
    GEODESIC_AXES,
    ICOSAHEDRON_AXES,
    bump,
    haar_frames,
    max_principal_angle,
    orientation_frames,
)
from flatserve.coordinates import OK
from flatserve.errors import InvalidInputError

#: Offsets of the coverage tests: uniform in [-OFFSET, OFFSET]^d.
OFFSET = 1e3
#: Value agreement "to rounding" between two interpolations of the same samples.
ROUNDING = 1e-9


def line_fn(o, v):
    """A smooth function of unoriented lines: of r (closest point) and a a^T."""
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    r = o - np.einsum("ni,ni->n", a, o)[:, None] * a
    return (np.sin(1.5 * r[:, 0]) + np.cos(r[:, 1]) + 0.5 * r[:, 2]
            + a[:, 0] * a[:, 1] + 0.7 * a[:, 2] ** 2 + 0.4 * a[:, 0] * a[:, 2])


def random_rays(rng, n, R=1.0, d=3):
    o = rng.uniform(-R, R, (n, d))
    v = rng.standard_normal((n, d))
    return o, v


def random_flats(rng, n, k, d, R):
    A = haar_frames(n, d, k, rng)
    b = rng.uniform(-R, R, (n, d))
    if k == 1:
        return Flats.from_rays(b, A[:, :, 0] * rng.choice([-1.0, 1.0], (n, 1)))
    return Flats.from_parametric(A, b)


# ------------------------------------------------------------------ geometry


def test_max_principal_angle_matches_svd():
    rng = np.random.default_rng(0)
    for k, d in [(1, 3), (2, 4), (2, 5), (3, 6)]:
        C = haar_frames(4, d, k, rng)
        F = haar_frames(300, d, k, rng)
        got = max_principal_angle(C, F)
        s = np.linalg.svd(np.einsum("cdi,ndj->ncij", C, F), compute_uv=False)
        want = np.arccos(np.clip(s[..., -1], -1, 1))
        np.testing.assert_allclose(got, want, atol=1e-7)


def test_normals_give_the_same_angles():
    rng = np.random.default_rng(1)
    f = random_flats(rng, 200, 3, 4, 1.0)  # k > d - k: normal frames used
    a = Atlas.covering(3, 4)
    A = orientation_frames(f, normals=False)
    s = np.linalg.svd(np.einsum("cdi,ndj->ncij", a.center_A, A), compute_uv=False)
    np.testing.assert_allclose(a.angles(f), np.arccos(np.clip(s[..., -1], -1, 1)), atol=1e-7)


def test_bump_is_a_smooth_step():
    inner, trusted = math.radians(20), math.radians(40)
    a = np.linspace(0, math.radians(50), 2001)
    b = bump(a, inner, trusted)
    assert b[a <= inner].min() == 1.0 and b[a >= trusted].max() == 0.0
    assert np.all(np.diff(b) <= 0)
    assert np.abs(np.diff(b)).max() < 2 * 1.875 * (a[1] - a[0]) / (trusted - inner)


def test_icosahedral_axes_cover_lines_in_r3():
    a = Atlas.from_centers(Flats.from_rays(np.zeros((6, 3)), ICOSAHEDRON_AXES))
    assert a.ncharts == 6
    # the face-centre direction is the farthest from every axis: 37.38 degrees
    face = ICOSAHEDRON_AXES[0] + ICOSAHEDRON_AXES[2] + ICOSAHEDRON_AXES[4]
    ang = np.degrees(max_principal_angle(a.frames, (face / np.linalg.norm(face))[None, :, None]))
    assert ang.min() == pytest.approx(37.377, abs=1e-3)
    assert a.info["covering_radius_deg"] <= ang.min() + 1e-9


def test_covering_of_lines_in_r3_is_narrow_and_within_the_memory_budget():
    """The default covering of (oriented) lines in R^3: the 16 axes of GEODESIC_AXES,
    every direction well inside a chart, at most 2 charts per sample on average."""
    a = Atlas.covering(1, 3)
    assert a.ncharts == 16 and (a.inner, a.trusted, a.reach) == COVER_RADII_3D
    # the 6 icosahedral axes are among the centres, and the 10 face axes
    assert (np.abs(ICOSAHEDRON_AXES @ GEODESIC_AXES.T).max(axis=1) > 1 - 1e-12).all()
    # measured again on a denser independent sample: the stored radius is the covering's
    fib = np.arange(1_000_000) + 0.5
    z = 1 - 2 * fib / fib.size
    phi = np.pi * (1 + 5 ** 0.5) * fib
    dirs = np.c_[np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z]
    dense = float(np.degrees(np.arccos(np.abs(dirs @ GEODESIC_AXES.T).max(axis=1).min())))
    radius = a.info["covering_radius_deg"]
    print(f"covering radius {radius:.3f} (dense check {dense:.3f}), margin to trusted "
          f"{a.trusted - radius:.2f} degrees")
    assert abs(dense - radius) < 0.05  # both measure the same supremum from below
    assert radius < a.trusted - COVER_MARGIN_DEG
    o = a.covering(1, 3, oriented=True)
    assert o.ncharts == 32 and o.info["covering_radius_deg"] == pytest.approx(radius, abs=0.05)
    rng = np.random.default_rng(4)
    v = rng.standard_normal((200_000, 3))
    dup = a.held(Flats.from_rays(np.zeros_like(v), v), a.reach).sum() / v.shape[0]
    dup_o = o.held(Flats.from_rays(np.zeros_like(v), v), o.reach).sum() / v.shape[0]
    print(f"duplication (uniform directions): {dup:.3f} (lines), {dup_o:.3f} (rays)")
    assert dup <= 2.0 and dup_o <= 2.0


# ------------------------------------------------------------------ coverage


@pytest.mark.parametrize("k,d", [(1, 3), (1, 4), (2, 4), (2, 5)])
def test_covering_atlas_charts_every_flat(k, d):
    """100 % of Haar-random flats, offsets up to 10^3, round-trip in a chart that routes
    them (the default atlas: balls in R^3, relative from R^4 on)."""
    from flatserve.atlas import RELATIVE_LIMIT_DEG

    atlas = Atlas.covering(k, d)
    assert atlas.relative == (d >= 4)
    print(f"({k}, {d}): {atlas.ncharts} charts, covering radius "
          f"{atlas.info['covering_radius_deg']:.2f} deg (trusted {atlas.trusted:g})")
    bound = RELATIVE_LIMIT_DEG - (atlas.reach - atlas.trusted) / 2 if atlas.relative \
        else atlas.trusted
    assert atlas.info["covering_radius_deg"] < bound - 1.0
    rng = np.random.default_rng(10 * k + d)
    n = 20_000
    f = random_flats(rng, n, k, d, OFFSET)
    ro = atlas.route(f, atlas.trusted)
    charted = np.zeros(n, dtype=bool)
    for c, rows in enumerate(ro.rows):
        if rows.size:
            co = atlas.bases[c].coordinates_of(f.take(rows))
            charted[rows[co.status == OK]] = True
    assert charted.all(), f"{(~charted).sum()} of {n} flats not charted"
    # every flat within reach of a centre round-trips there (samples go to all of them);
    # at offsets 10^3 the absolute ROUNDTRIP_TOL refuses a few near the reach (planes
    # in R^5: residual 2.7e-6), which their nearer charts hold
    f = random_flats(rng, n, k, d, 10.0)
    ro = atlas.route(f, atlas.reach)
    for c, rows in enumerate(ro.rows):
        if rows.size:
            co = atlas.bases[c].coordinates_of(f.take(rows))
            assert (co.status == OK).all(), (c, co.residual.max())


@pytest.mark.parametrize("unit", [0.5, 3.0])
def test_unit_is_the_same_chart_of_flats_scaled_by_its_inverse(unit):
    """A chart of unit u gives a flat the coordinates the unit-1 chart gives the
    flat scaled by 1/u about the origin (also off-origin centres); the unit is
    kept by to_dict/from_dict (what snapshots and the service store)."""
    rng = np.random.default_rng(11)
    o, v = random_rays(rng, 2000)
    c0, axes = rng.normal(size=(12, 3)), np.concatenate([ICOSAHEDRON_AXES, -ICOSAHEDRON_AXES])
    a = Atlas.from_centers(Flats.from_rays(c0, axes), oriented=True, unit=unit)
    s = Atlas.from_centers(Flats.from_rays(c0 / unit, axes), oriented=True)
    ro = a.route(Flats.from_rays(o, v), a.reach)  # each chart's domain
    for c, rows in enumerate(ro.rows):
        w = a.bases[c].coordinates_rays(o[rows], v[rows]).weights
        ws = s.bases[c].coordinates_rays(o[rows] / unit, v[rows]).weights
        np.testing.assert_allclose(w, ws, rtol=0, atol=1e-8)
    b = Atlas.from_dict(a.to_dict())
    assert b.unit == unit
    np.testing.assert_array_equal(b.bases[3].r, a.bases[3].r)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "1", True])
def test_unit_must_be_a_positive_length(bad):
    with pytest.raises(InvalidInputError) as exc:
        Atlas.covering(1, 3, unit=bad)
    assert exc.value.argument == "unit"
    with pytest.raises(InvalidInputError) as exc:
        object_unit(bad)
    assert exc.value.argument == "radius"


def test_object_unit_is_the_mean_visible_depth_of_a_ball():
    """2R/3: sqrt(R^2 - rho^2) averaged over the disc rho < R (a seeded sample)."""
    rng = np.random.default_rng(5)
    R = 0.8
    rho = R * np.sqrt(rng.uniform(size=400_000))  # uniform over the disc
    assert object_unit(R) == pytest.approx(np.sqrt(R * R - rho * rho).mean(), rel=2e-3)


def rays_at_a_ball(rng, n, center, R):
    """Rays of every direction whose distances from ``center`` are uniform over the
    disc of radius ``R`` (rays that meet a ball: its silhouette's disc)."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    e1 = np.cross(v, rng.normal(size=(n, 3)))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(v, e1)
    rho, phi = R * np.sqrt(rng.uniform(size=n)), rng.uniform(0, 2 * np.pi, n)
    p = center + rho[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return p - rng.uniform(1, 3, (n, 1)) * v, v  # origins before the ball


def test_data_unit_is_the_object_unit_of_the_ball_the_rays_meet():
    """Rays meeting a ball of radius R: the mean distance from their least-squares
    centre is object_unit(R), wherever the ball is; the unit scales with the data;
    rays of one repeated (background) value are left out; rays through one point
    have no length: the default."""
    rng = np.random.default_rng(31)
    c = np.array([3.0, -1.0, 2.0])
    o, v = rays_at_a_ball(rng, 50_000, c, 0.6)
    f = Flats.from_rays(o, v)
    u = data_unit(f, rng.uniform(size=(f.n, 2)))
    assert u == pytest.approx(object_unit(0.6), rel=0.01)
    assert data_unit(Flats.from_rays(7.0 * o, v)) == pytest.approx(7.0 * data_unit(f), rel=1e-9)
    # a background: rays farther out (missing the ball), all of one value, 30 % of them
    bo, bv = rays_at_a_ball(rng, 21_000, c, 3.0)
    far = np.linalg.norm(np.cross(bo - c, bv), axis=1) > 0.6
    bo, bv = bo[far][:20_000], bv[far][:20_000]
    vals = np.r_[rng.uniform(size=(f.n, 2)), np.tile([0.25, 0.5], (bo.shape[0], 1))]
    both = Flats.from_rays(np.r_[o, bo], np.r_[v, bv])
    assert data_unit(both, vals) == pytest.approx(u, rel=0.01)
    assert data_unit(both) > 1.3 * u  # without values every ray counts
    for point in (np.zeros(3), c):
        through = Flats.from_rays(point - v[:100], v[:100])
        assert data_unit(through) == DEFAULT_UNIT


def test_a_unit_from_the_data_is_chosen_by_the_first_batch_and_kept(tmp_path):
    """Atlas(unit=None): the field's first batch chooses data_unit of its rows; the
    field then answers as the atlas built with that unit; later batches, snapshots
    and settle_unit keep it; a batch charted in another unit is refused."""
    rng = np.random.default_rng(32)
    o, v = rays_at_a_ball(rng, 6000, np.zeros(3), 2.0)
    vals = np.c_[np.sin(o[:, 0]), v[:, 1]]
    f = Flats.from_rays(o, v)
    first, second = f.take(np.arange(4000)), f.take(np.arange(4000, 6000))
    auto = AtlasField(Atlas.covering(1, 3, oriented=True, unit=None), channels=2)
    assert auto.unit_pending and auto.unit_from_data
    assert auto.describe()["atlas"]["unit"] is None
    empty = AtlasField.from_bytes(auto.to_bytes())
    assert empty.unit_pending  # an empty snapshot still chooses later
    auto.add(first, vals[:4000])
    u = data_unit(first, vals[:4000])
    assert not auto.unit_pending and auto.atlas.unit == u and abs(u - 1.0) > 0.1
    assert auto.describe()["atlas"]["unit"] == u
    assert auto.describe()["atlas"]["unit_from"] == "data"
    auto.add(second, vals[4000:])
    assert auto.atlas.unit == u
    fixed = AtlasField(Atlas.covering(1, 3, oriented=True, unit=u), channels=2)
    fixed.add(first, vals[:4000])
    fixed.add(second, vals[4000:])
    q = Flats.from_rays(*rays_at_a_ball(rng, 2000, np.zeros(3), 1.5))
    got, want = auto.query(q), fixed.query(q)
    assert want.inside.mean() > 0.5
    np.testing.assert_array_equal(got.values, want.values)
    back = AtlasField.from_bytes(auto.to_bytes())
    assert back.atlas.unit == u and not back.unit_pending and not back.unit_from_data
    assert back.describe()["atlas"]["unit_from"] == "data"
    np.testing.assert_array_equal(back.query(q).values, want.values)
    assert auto.settle_unit(u) is False  # asked again: kept
    with pytest.raises(InvalidInputError, match="chosen from its first batch"):
        auto.settle_unit(2 * u)
    assert auto.settle_unit(2 * u, if_empty=True) is False and auto.atlas.unit == u
    with pytest.raises(InvalidInputError, match="given"):
        fixed.settle_unit(2 * u)
    # a writer charts a batch in its own unit without changing the field (in_unit);
    # the field refuses it until it takes that unit, then holds what `fixed` holds
    late = AtlasField(Atlas.covering(1, 3, oriented=True, unit=None), channels=2)
    assert late.in_unit(u) is not late and auto.in_unit(u) is auto
    batch = late.in_unit(u).prepare(first, vals[:4000])
    assert batch.unit == u and late.unit_pending and late.nstored == 0
    with pytest.raises(InvalidInputError, match="not taken a unit"):
        late.insert_prepared(batch)
    assert late.settle_unit(2 * u) and late.atlas.unit == 2 * u  # still open: no insert
    with pytest.raises(InvalidInputError, match="prepare it again"):
        late.insert_prepared(batch)
    assert AtlasField.from_bytes(late.to_bytes()).unit_from_data  # (a snapshot too)
    late.settle_unit(u)
    late.insert_prepared(batch)
    assert not late.unit_from_data and late.settle_unit(2 * u, if_empty=True) is False
    once = AtlasField(Atlas.covering(1, 3, oriented=True, unit=u), channels=2)
    once.add(first, vals[:4000])
    np.testing.assert_array_equal(late.query(q).values, once.query(q).values)


def test_oriented_covering_radius_and_routing():
    a = Atlas.covering(1, 3, oriented=True)
    assert a.ncharts == 32
    assert a.info["covering_radius_deg"] < a.trusted - COVER_MARGIN_DEG
    rng = np.random.default_rng(3)
    o, v = random_rays(rng, 1000)
    ro = a.route(Flats.from_rays(o, v), a.reach)
    ro2 = a.route(Flats.from_rays(o, -v), a.reach)
    # a ray and its reverse never share a chart; the reverse goes to the negated centres
    for c in range(16):
        assert np.intersect1d(ro.rows[c], ro2.rows[c]).size == 0
        np.testing.assert_array_equal(ro.rows[c], ro2.rows[c + 16])


def test_atlas_refuses_what_does_not_cover():
    Q, r = np.eye(3)[None] - np.outer([0, 0, 1.0], [0, 0, 1.0])[None], np.zeros((1, 3))
    axes = Flats.from_quadrics(np.stack([np.eye(3) - np.outer(e, e) for e in np.eye(3)]),
                               np.zeros((3, 3)), 1)
    with pytest.raises(InvalidInputError) as exc:
        Atlas.from_centers(axes)  # the 3 coordinate axes leave 54.7 degrees
    assert exc.value.argument == "centers" and "do not cover" in str(exc.value)
    worst = float(str(exc.value).split(" is ")[1].split(" degrees")[0])
    assert 54.0 < worst <= 54.74  # the cube diagonals: arccos(1/sqrt(3)) = 54.74
    ico = Flats.from_rays(np.zeros((6, 3)), ICOSAHEDRON_AXES)
    assert Atlas.from_centers(ico).info["covering_radius_deg"] < 37.5
    with pytest.raises(InvalidInputError) as exc:
        Atlas.from_centers(ico, scales=1e-13)  # a scale that collapses the charts
    assert exc.value.argument == "centers"
    del Q, r


def test_oriented_atlas_refuses_orientation_free_forms():
    field = AtlasField(Atlas.covering(1, 3, oriented=True))
    rng = np.random.default_rng(4)
    o, v = random_rays(rng, 10)
    f = Flats.from_rays(o, v)
    Q, r = f.quadrics()
    for flats, arg in [(Flats.from_quadrics(Q, r, 1), "Q"),
                       (Flats.from_parametric(v[:, :, None], o), "A")]:
        with pytest.raises(InvalidInputError) as exc:
            field.add(flats, np.zeros(10))
        assert exc.value.argument == arg and repr(flats.form) in str(exc.value)
        with pytest.raises(InvalidInputError):
            field.query(flats)


# ------------------------------------------------------------------ fields


@pytest.fixture(scope="module")
def lines_field():
    """A covering atlas field of lines in R^3 with a smooth function, densely sampled."""
    rng = np.random.default_rng(7)
    o, v = random_rays(rng, 40_000)
    field = AtlasField(Atlas.covering(1, 3), channels=1)
    res = field.add(Flats.from_rays(o, v), line_fn(o, v))
    assert res.accepted == len(o) and res.rejected.size == 0
    return field, o, v


def test_every_sample_accepted_and_reproduced(lines_field):
    field, o, v = lines_field
    assert field.nsamples == len(o)
    assert 1.0 < field.duplication < 2.0
    desc = field.describe()
    assert [c["samples"] for c in desc["charts"]] == field.samples_per_chart
    assert sum(field.samples_per_chart) == field.nstored
    q = field.query(Flats.from_rays(o[:3000], v[:3000]))
    assert q.status.tolist() == [OK] * 3000 and q.inside.all()
    np.testing.assert_allclose(q.values[:, 0], line_fn(o[:3000], v[:3000]), atol=1e-9)
    # the reversed rays are the same lines
    q2 = field.query(Flats.from_rays(o[:3000], -v[:3000]))
    np.testing.assert_allclose(q2.values, q.values, atol=1e-12)


def test_weights_recombine_the_values(lines_field):
    field, o, v = lines_field
    rng = np.random.default_rng(8)
    qo, qv = random_rays(rng, 2000, R=0.8)
    q = field.query(Flats.from_rays(qo, qv), return_weights=True)
    ok = q.inside
    assert ok.mean() > 0.95
    vals = np.zeros(len(qo))
    for c, f in enumerate(field.fields):
        m = (q.charts == c)[:, :, None] & (q.ids >= 0)
        vals += np.where(m, q.weights * f.values[np.where(m, q.ids, 0), 0], 0).sum(axis=(1, 2))
    np.testing.assert_allclose(vals[ok], q.values[ok, 0], atol=1e-9)
    np.testing.assert_allclose(np.nansum(q.weights, axis=(1, 2))[ok], 1.0, atol=1e-9)


def test_deep_inside_a_chart_equals_the_single_chart_field(lines_field):
    field, o, v = lines_field
    atlas = field.atlas
    c = 2
    single = atlas.chart_field(c, channels=1)
    single.add(Flats.from_rays(o, v), line_fn(o, v))  # rejects what its chart cannot hold
    rng = np.random.default_rng(9)
    # directions within (nearest other centre - trusted) of centre c: every other
    # centre is farther than trusted
    u = atlas.frames[c, :, 0]
    sep = np.degrees(np.sort(max_principal_angle(atlas.frames, u[None, :, None])[0])[1])
    deep = sep - atlas.trusted - 0.1
    w = rng.standard_normal((3000, 3))
    w -= np.outer(w @ u, u)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    t = np.radians(rng.uniform(0, deep, 3000))
    qv = np.cos(t)[:, None] * u + np.sin(t)[:, None] * w
    qo = rng.uniform(-0.8, 0.8, (3000, 3))
    f = Flats.from_rays(qo, qv)
    assert (np.sort(atlas.angles(f), axis=1)[:, 1] > math.radians(atlas.trusted)).all()
    a, b = field.query(f), single.query(f)
    both = a.inside & b.inside
    assert both.mean() > 0.95
    np.testing.assert_allclose(a.values[both], b.values[both], rtol=0, atol=ROUNDING)


def sweep(rng, n_paths=24, step_deg=0.05):
    """Query rays along great circles of directions, origin fixed per path."""
    t = np.radians(np.arange(0, 180, step_deg))
    o_all, v_all = [], []
    for _ in range(n_paths):
        u1, u2 = np.linalg.qr(rng.standard_normal((3, 2)))[0].T
        o = rng.uniform(-0.5, 0.5, 3)
        v_all.append(np.cos(t)[:, None] * u1 + np.sin(t)[:, None] * u2)
        o_all.append(np.broadcast_to(o, (t.size, 3)))
    return np.array(o_all), np.array(v_all)


def test_no_seam_across_chart_borders(lines_field):
    """Largest jump between neighbouring queries where a chart's weight starts or stops
    is no larger than the largest jump between neighbours inside one chart."""
    field, _, _ = lines_field
    atlas = field.atlas
    rng = np.random.default_rng(11)
    O, V = sweep(rng)
    P, T = O.shape[:2]
    f = Flats.from_rays(O.reshape(-1, 3), V.reshape(-1, 3))
    q = field.query(f)
    assert q.inside.all()
    vals = q.values[:, 0].reshape(P, T)
    held = (atlas.angles(f) < math.radians(atlas.trusted)).reshape(P, T, -1)
    jump = np.abs(np.diff(vals, axis=1))
    border = (held[:, 1:] != held[:, :-1]).any(axis=2)
    one = (held[:, 1:].sum(axis=2) == 1) & (held[:, :-1].sum(axis=2) == 1) & ~border
    assert border.sum() >= 4 * P and one.sum() > 100
    print(f"largest jump at {border.sum()} border steps {jump[border].max():.4g}, "
          f"inside one chart ({one.sum()} steps) {jump[one].max():.4g}")
    assert jump[border].max() <= jump[one].max()

    # the oracle has power: answering from the nearest chart alone leaves a seam
    near = atlas.angles(f).argmin(axis=1)
    hard = np.empty(len(near))
    for c in range(atlas.ncharts):
        rows = np.flatnonzero(near == c)
        hard[rows] = field.fields[c].query(f.take(rows)).values[:, 0]
    hard = hard.reshape(P, T)
    switch = near.reshape(P, T)[:, 1:] != near.reshape(P, T)[:, :-1]
    hjump = np.abs(np.diff(hard, axis=1))
    print(f"nearest chart only: largest jump at a switch {hjump[switch].max():.4g}")
    assert hjump[switch].max() > jump[one].max()


def ray_fn(o, v):
    """A smooth function of oriented rays: reversing a ray flips the last term."""
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    return line_fn(o, v) + 1.5 * a[:, 2] - 0.8 * a[:, 0]


def test_oriented_rays_keep_their_direction():
    rng = np.random.default_rng(12)
    o, v = random_rays(rng, 20_000)
    field = AtlasField(Atlas.covering(1, 3, oriented=True), channels=1)
    res = field.add(Flats.from_rays(np.r_[o, o], np.r_[v, -v]), ray_fn(np.r_[o, o], np.r_[v, -v]))
    assert res.accepted == 40_000 and res.duplicates == 0
    qf = field.query(Flats.from_rays(o[:2000], v[:2000]))
    qb = field.query(Flats.from_rays(o[:2000], -v[:2000]))
    np.testing.assert_allclose(qf.values[:, 0], ray_fn(o[:2000], v[:2000]), atol=1e-9)
    np.testing.assert_allclose(qb.values[:, 0], ray_fn(o[:2000], -v[:2000]), atol=1e-9)
    # new rays: a ray and its reverse get their own values
    qo, qv = random_rays(rng, 2000, R=0.5)
    a = field.query(Flats.from_rays(qo, qv)).values[:, 0]
    b = field.query(Flats.from_rays(qo, -qv)).values[:, 0]
    assert np.isfinite(a).all() and np.isfinite(b).all()
    err_a = np.abs(a - ray_fn(qo, qv))
    err_b = np.abs(b - ray_fn(qo, -qv))
    diff = np.abs(ray_fn(qo, qv) - ray_fn(qo, -qv))
    print(f"oriented: median error {np.median(err_a):.4f} / {np.median(err_b):.4f}, "
          f"median front-back difference {np.median(diff):.3f}")
    assert np.median(err_a) < 0.1 * np.median(diff) and np.median(err_b) < 0.1 * np.median(diff)
    # an unoriented field cannot tell them apart
    un = AtlasField(Atlas.covering(1, 3))
    un.add(Flats.from_rays(o, v), ray_fn(o, v))
    ua = un.query(Flats.from_rays(qo, qv)).values
    np.testing.assert_array_equal(ua, un.query(Flats.from_rays(qo, -qv)).values)


def test_data_driven_atlas_rejects_with_a_reason():
    rng = np.random.default_rng(13)
    # rays around +z and around +x (two clusters), none elsewhere
    n = 4000
    o = np.c_[rng.uniform(-1, 1, (n, 2)), np.full(n, -3.0)]
    v = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), np.ones(n)]
    o2 = o[:, [2, 1, 0]]
    v2 = v[:, [2, 1, 0]]
    f = Flats.from_rays(np.r_[o, o2], np.r_[v, v2])
    atlas = Atlas.for_samples(f)
    assert atlas.ncharts == 2, atlas.info
    assert atlas.info["max_sample_angle_deg"] < 30
    field = AtlasField(atlas)
    vals = line_fn(np.r_[o, o2], np.r_[v, v2])
    res = field.add(f, vals)
    assert res.accepted == 2 * n
    q = field.query(f.take(np.arange(0, 2 * n, 7)))
    np.testing.assert_allclose(q.values[:, 0], vals[::7], atol=1e-9)
    # a ray along y is 90 degrees from both clusters: rejected, with its reason
    y = Flats.from_rays([[0, 0, 0.0]], [[0, 1.0, 0]])
    res = field.add(y, [1.0])
    assert res.accepted == 0 and res.rejected.tolist() == [0]
    nearest = math.degrees(atlas.angles(y).min())
    assert nearest > 85
    assert "outside every chart's domain" in res.reasons[0] and f"{nearest:.2f}" in res.reasons[0]
    assert field.query(Flats.from_rays([[0, 0, 0.0]], [[0, 1.0, 0]])).status[0] != OK


def test_save_and_load(tmp_path, lines_field):
    field, o, v = lines_field
    path = tmp_path / "f.atlas"
    field.save(path)
    assert path.is_file()  # one file (the service renames it into place)
    back = AtlasField.load(path)
    assert back.nsamples == field.nsamples and back.nstored == field.nstored
    assert back.nsimplex == field.nsimplex and back.nrejected == field.nrejected
    assert back.atlas.to_dict() == field.atlas.to_dict()
    f = Flats.from_rays(o[:500] * 0.9, v[:500])
    np.testing.assert_array_equal(back.query(f).values, field.query(f).values)
    from flatserve.errors import SnapshotError
    data = path.read_bytes()
    for bad in (data[:-1], data + b"\0", b"FSFIELD\0" + data[8:], data[:100]):
        path.write_bytes(bad)
        with pytest.raises(SnapshotError):
            AtlasField.load(path)


def test_points_have_one_chart():
    """k = 0: every point has the same (empty) orientation: one chart, all accepted."""
    rng = np.random.default_rng(3)
    atlas = Atlas.covering(0, 3)
    assert atlas.ncharts == 1 and atlas.info["covering_radius_deg"] == 0.0
    field = AtlasField(atlas)
    r = rng.normal(size=(300, 3))
    f = Flats.from_quadrics(np.broadcast_to(np.eye(3), (300, 3, 3)), r, 0)
    assert field.add(f, r[:, 0]).accepted == 300
    np.testing.assert_allclose(field.query(f.take(np.arange(20))).values[:, 0], r[:20, 0],
                               atol=1e-9)


def test_planes_in_r4_field():
    """The same properties hold off lines: planes in R^4, sample values reproduced."""
    rng = np.random.default_rng(14)
    atlas = Atlas.covering(2, 4)
    f = random_flats(rng, 3000, 2, 4, 1.0)
    Q, r = f.quadrics()
    vals = np.sin(r[:, 0]) + Q[:, 0, 1]
    field = AtlasField(atlas)
    res = field.add(f, vals)
    assert res.accepted == 3000
    q = field.query(f.take(np.arange(300)))
    assert (q.status == OK).all()
    np.testing.assert_allclose(q.values[:, 0], vals[:300], atol=1e-8)


@pytest.mark.parametrize("k, d, oriented", [(1, 3, True), (1, 3, False), (2, 4, False),
                                             (3, 4, False)])
def test_held_counts_what_route_routes(k, d, oriented):
    """Atlas.held: per chart, the sizes of Atlas.route's rows (the same test; a
    relative atlas's held is route's, checked against an SVD in the relative tests)."""
    rng = np.random.default_rng(5)
    at = Atlas.covering(k, d, oriented=oriented, relative=False)
    n = 2000
    f = (Flats.from_rays(rng.normal(size=(n, d)), rng.normal(size=(n, d))) if k == 1 else
         Flats.from_parametric(rng.normal(size=(n, d, k)), rng.normal(size=(n, d))))
    for radius in (at.trusted, at.reach):
        held = at.held(f, radius)
        assert held.shape == (at.ncharts,)
        np.testing.assert_array_equal(held, [r.size for r in at.route(f, radius).rows])
    assert held.sum() > n  # charts overlap: some flats are held by several


def test_sliced_insert_equals_the_whole_insert():
    """AtlasField.insert_prepared(slice_rows=...) (chart by chart, in slices) leaves the
    field as the whole insert does: the same samples per chart, cells and answers."""
    rng = np.random.default_rng(6)
    o, v = rng.uniform(-1, 1, (3000, 3)), rng.normal(size=(3000, 3))
    flats, val = Flats.from_rays(o, v), line_fn(o, v)
    whole, sliced = AtlasField(Atlas.covering(1, 3)), AtlasField(Atlas.covering(1, 3))
    for part in (slice(0, 2000), slice(1500, 3000)):  # the overlap: duplicates
        a = whole.insert_prepared(whole.prepare(flats.take(np.arange(3000)[part]), val[part]))
        b = sliced.insert_prepared(sliced.prepare(flats.take(np.arange(3000)[part]), val[part]),
                                   slice_rows=97)
        assert (a.accepted, a.duplicates, a.nsamples) == (b.accepted, b.duplicates, b.nsamples)
    assert a.duplicates == 500
    assert whole.samples_per_chart == sliced.samples_per_chart
    assert (whole.nsimplex, whole.nrejected) == (sliced.nsimplex, sliced.nrejected)
    q = Flats.from_rays(rng.uniform(-0.5, 0.5, (500, 3)), rng.normal(size=(500, 3)))
    np.testing.assert_allclose(sliced.query(q).values, whole.query(q).values, rtol=0,
                               atol=ROUNDING, equal_nan=True)
    with pytest.raises(InvalidInputError):
        sliced.insert_prepared(sliced.prepare(flats.take([0]), val[:1]), slice_rows=0)


def test_a_sample_queried_alone_gets_its_value_back():
    """Each sample, queried on its own, is found (a vertex on a chart's hull
    included: its point is the same bits as when it was inserted) and answers
    its own value."""
    rng = np.random.default_rng(3)
    n = 500
    o = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    v = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)] - o
    vals = rng.uniform(size=(n, 1))
    field = AtlasField(Atlas.covering(1, 3), channels=1)
    field.add(Flats.from_rays(o, v), vals)
    for i in range(0, n, 3):
        got = field.query(Flats.from_rays(o[i:i + 1], v[i:i + 1]))
        assert got.inside[0], i
        np.testing.assert_allclose(got.values[0], vals[i], rtol=0, atol=1e-9)


@pytest.mark.parametrize("oriented, k, d, relative", [(False, 1, 3, False),
                                                      (True, 1, 3, False),
                                                      (True, 1, 3, True), (False, 2, 4, True)])
def test_a_flats_routing_does_not_depend_on_its_batch(oriented, k, d, relative, monkeypatch):
    """Which charts hold a flat and at what angle (hence its blending weights; a
    relative atlas's nearest angle too) are the same bits whether the flat is routed
    alone, in a small batch or in a large one (a relative atlas routes in blocks:
    made small here): a query near a border must not change charts with its company."""
    import flatserve.atlas

    monkeypatch.setattr(flatserve.atlas, "RELATIVE_BLOCK", 1000)
    rng = np.random.default_rng(12)
    at = Atlas.covering(k, d, oriented=oriented, relative=relative)
    n = 3000
    flats = random_flats(rng, n, k, d, 1.0)
    whole = at.route(flats, at.trusted)
    for size in (1, 7, 333):
        for lo in range(0, n if size > 1 else 300, size):
            part = at.route(flats.take(np.arange(lo, min(n, lo + size))), at.trusted)
            for c in range(at.ncharts):
                sel = (whole.rows[c] >= lo) & (whole.rows[c] < lo + size)
                np.testing.assert_array_equal(part.rows[c], whole.rows[c][sel] - lo)
                assert part.angles[c].tobytes() == whole.angles[c][sel].tobytes()
            got = part.nearest_angle.tobytes()
            assert got == whole.nearest_angle[lo:lo + size].tobytes()


# ------------------------------------------------------------ relative atlases
RELATIVE_KINDS = [(1, 4), (2, 4), (1, 3)]


@pytest.mark.parametrize("k, d", RELATIVE_KINDS)
def test_a_relative_atlas_routes_by_the_angle_beyond_the_nearest_centre(k, d):
    """Each flat goes to the charts whose centre is within ``radius`` of its nearest
    centre's angle (and below the absolute limit), the nearest always: the angles
    of an SVD (max_principal_angle) say the same, except within rounding of a
    limit."""
    from flatserve.atlas import RELATIVE_LIMIT_DEG

    rng = np.random.default_rng(31)
    at = Atlas.covering(k, d, relative=True)
    f = random_flats(rng, 3000, k, d, 1.0)
    ang = at.angles(f)  # (n, c), by SVD
    best = ang.min(axis=1)
    for radius in (at.trusted, at.reach):
        ro = at.route(f, radius)
        limit = np.minimum(best + math.radians(radius), math.radians(RELATIVE_LIMIT_DEG))
        held = np.zeros_like(ang, dtype=bool)
        for c, rows in enumerate(ro.rows):
            held[rows, c] = True
        want = ang <= limit[:, None]
        close = np.abs(ang - limit[:, None]) < 1e-9
        assert not (held != want)[~close].any()
        assert held[np.arange(f.n), ang.argmin(axis=1)].all()  # the nearest always
        np.testing.assert_allclose(ro.nearest_angle, best, atol=1e-9)
        np.testing.assert_array_equal(at.held(f, radius), held.sum(axis=0))


@pytest.mark.parametrize("k, d", [(1, 4), (2, 4)])
def test_a_relative_chart_holds_the_samples_around_every_query_it_answers(k, d):
    """A chart that answers a query (its angle within ``trusted`` of the nearest
    centre's) stores every flat within ``(reach - trusted) / 2`` of it (the angles of
    a flat move by at most its distance), up to the absolute limit: the seam is wide
    enough for the chart's triangulation around its queries."""
    from flatserve.atlas import RELATIVE_LIMIT_DEG

    rng = np.random.default_rng(32)
    at = Atlas.covering(k, d, relative=True)
    delta = math.radians((at.reach - at.trusted) / 2)
    q = random_flats(rng, 400, k, d, 1.0)
    A = orientation_frames(q, normals=False)
    # neighbours: each query's frame turned a little, then re-orthonormalised
    B = np.linalg.qr(A + rng.normal(scale=0.025, size=A.shape))[0]
    s = Flats.from_parametric(B, rng.uniform(-1, 1, (q.n, d)))
    dist = np.array([max_principal_angle(A[i:i + 1], B[i:i + 1])[0, 0] for i in range(q.n)])
    near = dist <= delta
    assert near.mean() > 0.5
    asked, stored = at.route(q, at.trusted), at.route(s, at.reach)
    aq = at.angles(q)
    checked = 0
    for c in range(at.ncharts):
        rows = asked.rows[c]
        rows = rows[near[rows] & (aq[rows, c] + delta < math.radians(RELATIVE_LIMIT_DEG) - 1e-9)]
        assert np.isin(rows, stored.rows[c]).all(), c
        checked += rows.size
    assert checked > q.n  # queries answered by more than one chart were checked
    if at.dense_reach is not None:  # a dense chart's narrower seam: (dense_reach - trusted) / 2
        half = math.radians((at.dense_reach - at.trusted) / 2)
        B = np.linalg.qr(A + rng.normal(scale=0.4 * half, size=A.shape))[0]
        s2 = Flats.from_parametric(B, rng.uniform(-1, 1, (q.n, d)))
        stored = at.route(s2, at.dense_reach)
        close = np.array([max_principal_angle(A[i:i + 1], B[i:i + 1])[0, 0]
                          for i in range(q.n)]) <= half
        assert close.mean() > 0.5
        for c in range(at.ncharts):
            rows = asked.rows[c]
            rows = rows[close[rows]
                        & (aq[rows, c] + half < math.radians(RELATIVE_LIMIT_DEG) - 1e-9)]
            assert np.isin(rows, stored.rows[c]).all(), c
    # without the seam (reach just past trusted) some of those neighbours are missing
    narrow = Atlas.covering(k, d, relative=True, reach=at.trusted + 0.5)
    stored = narrow.route(s, narrow.reach)
    missing = sum(int((~np.isin(rows[near[rows]], stored.rows[c])).sum())
                  for c, rows in enumerate(narrow.route(q, narrow.trusted).rows))
    assert missing > 0
    # and with none at all the atlas is refused, naming the radius
    with pytest.raises(InvalidInputError, match="reach: a relative atlas needs reach > trusted"):
        Atlas.covering(k, d, relative=True, reach=at.trusted)
    # (one stored before the check still loads)
    assert Atlas.from_dict({**at.to_dict(), "reach": at.trusted, "dense_reach": None,
                            "dense_after": None, "seam_spacing": None}).reach == at.trusted


def test_a_relative_atlas_stores_fewer_copies_and_keeps_what_it_is():
    """Lines and planes in R^4: a sample of the default (relative) atlas is stored in
    fewer charts than by balls about the centres (the open issue's target: at most
    2.5 for lines; planes, on their 59 charts with the seam of 14 alone, 3.42 in
    docs/costs.md, fewer once dense: the tests above); R^3 keeps balls; the
    setting survives to_dict, with_unit and a field file; a bad value is refused
    naming it."""
    rng = np.random.default_rng(33)
    for k, most in ((1, 2.5), (2, 4.0)):
        f = random_flats(rng, 4000, k, 4, 1.0)
        ball, rel = Atlas.covering(k, 4, relative=False), Atlas.covering(k, 4)
        copies = [at.held(f, at.reach).sum() / f.n for at in (ball, rel)]
        assert 1.0 < copies[1] <= most < copies[0], (k, copies)
    at = Atlas.covering(1, 4, relative=True)
    assert Atlas.from_dict(at.to_dict()).relative and at.with_unit(2.0).relative
    assert not Atlas.from_dict(Atlas.covering(1, 4, relative=False).to_dict()).relative
    assert Atlas.covering(1, 4).relative and not Atlas.covering(1, 3).relative
    assert Atlas.describe_spec(at.to_dict())["atlas"]["relative"] is True
    with pytest.raises(InvalidInputError, match="relative"):
        Atlas(1, 3, at.center_A[:1, :3], None, np.zeros((1, 3)), [1.0], relative="yes")


def expected_dense_counts(at, flats):
    """Per chart, how many samples a dense-seam atlas stores of ``flats`` inserted in
    order, counted apart from the field: every row within ``dense_reach`` of its
    nearest centre's angle, and a row beyond it only while fewer than ``dense_after``
    rows before it had this chart as their nearest."""
    ro = at.route(flats, at.reach)
    counts = []
    for c, (rows, ang) in enumerate(zip(ro.rows, ro.angles)):
        own_before = np.cumsum(ro.nearest[rows] == c) - (ro.nearest[rows] == c)
        beyond = np.degrees(ang - ro.nearest_angle[rows]) > at.dense_reach
        counts.append(int((~beyond | (own_before < at.dense_after)).sum()))
    return counts


def expected_net_counts(at, flats):
    """Per chart, how many samples an atlas with a net of its outer seam stores of
    ``flats`` inserted in order, counted apart from the field (the rows one by one,
    a plain loop): every row within ``dense_reach`` of its nearest centre's angle,
    and a row beyond it only while fewer than ``dense_after`` rows before it had
    this chart as their nearest (if given) and if no row the chart stored before
    it lies within ``seam_spacing / scale`` of it in the chart's coordinates."""
    ro = at.route(flats, at.reach)
    counts = []
    for c, (rows, ang) in enumerate(zip(ro.rows, ro.angles)):
        x = at.chart_field(c).chart(flats.take(rows)).points
        beyond = np.degrees(ang - ro.nearest_angle[rows]) > at.dense_reach
        radius = at.seam_spacing / at.scales[c]
        own = 0
        held: list = []
        for i in range(rows.size):
            dense = at.dense_after is not None and own >= at.dense_after
            own += int(ro.nearest[rows[i]] == c)
            if beyond[i] and (dense or held and np.sqrt(
                    ((np.array(held) - x[i]) ** 2).sum(axis=1)).min() <= radius):
                continue
            held.append(x[i])
        counts.append(len(held))
    return counts


# (in a given unit: the expected counts are of the charts as built, which a unit
# chosen from the first batch would rebuild)
SEAMS = {
    # the default for planes in R^4: every sample up to 7 degrees, beyond that a net
    "net": (dict(unit=DEFAULT_UNIT), expected_net_counts),
    # a user's choice: the seam narrowed to 9 once a chart holds 25 own samples
    "dense": (dict(relative=True, inner=2.0, trusted=6.0, reach=14.0, dense_reach=9.0,
                   dense_after=25, unit=DEFAULT_UNIT), expected_dense_counts),
    # both: a net beyond 7 while a chart holds fewer than 30 own samples, then nothing
    "both": (dict(relative=True, inner=2.0, trusted=6.0, reach=14.0, dense_reach=7.0,
                  dense_after=30, seam_spacing=0.8, unit=DEFAULT_UNIT), expected_net_counts),
}


@pytest.mark.parametrize("seam", sorted(SEAMS))
def test_a_thinner_seam_is_stored_alike_whatever_the_batches(seam):
    """Planes in R^4, a net of the outer seam (the default) or a seam narrowed once
    dense: each chart stores what an independent count of the rows in order says;
    the same samples in other batches, in slices, or through a file in the middle
    are stored alike and answer bit for bit, as are a shard worker's charts; fewer
    copies than the seam of 14 alone on the same charts, more than ``dense_reach``
    alone."""
    rng = np.random.default_rng(41)
    kw, expected = SEAMS[seam]
    at = Atlas.covering(2, 4, **kw)
    assert (at.ncharts, at.reach) == (59, 14.0)
    f = random_flats(rng, 2500, 2, 4, 1.0)
    val = np.sin(f.quadrics()[1][:, :1] * 2.0)
    q = random_flats(rng, 400, 2, 4, 1.0)
    whole = AtlasField(at, 1)
    whole.add(f, val)
    stored = [g.nsamples for g in whole.fields]
    assert stored == expected(at, f)
    wide = at.held(f, at.reach).sum()
    narrow = at.held(f, at.dense_reach).sum()
    assert narrow < sum(stored) < wide, (narrow, sum(stored), wide)
    want = whole.query(q)
    assert want.inside.mean() > 0.9
    cuts = [0, 1, 40, 41, 700, 1900, 2500]
    parts = AtlasField(at, 1)
    for lo, hi in zip(cuts, cuts[1:]):
        rows = np.arange(lo, hi)
        parts.insert_prepared(parts.prepare(f.take(rows), val[rows]), slice_rows=97)
        if hi == 700:  # through a file: what the charts hold goes with it
            parts = AtlasField.from_bytes(parts.to_bytes())
    assert [g.nsamples for g in parts.fields] == stored
    got = parts.query(q)
    np.testing.assert_array_equal(got.values, want.values)
    # shards (a shard worker prepares and inserts its charts only, following the
    # batches): each stores its charts' samples as the whole field does
    halves = (set(range(0, at.ncharts, 2)), set(range(1, at.ncharts, 2)))
    for only in halves:
        shard = AtlasField(at, 1)
        for lo, hi in zip(cuts, cuts[1:]):
            rows = np.arange(lo, hi)
            shard.insert_prepared(shard.prepare(f.take(rows), val[rows], only=only),
                                  slice_rows=61)
            if hi == 700:  # restored from a file as a shard worker restores its charts
                shard = AtlasField.from_bytes(shard.to_bytes(), only=only)
        assert [shard.fields[c].nsamples for c in sorted(only)] == \
            [stored[c] for c in sorted(only)]
    if seam == "dense":  # dense from the start: the seam of 9 alone; never: 14
        for after, radius in ((0, at.dense_reach), (10**6, at.reach)):
            other = AtlasField(Atlas.from_dict({**at.to_dict(), "dense_after": after}), 1)
            other.add(f, val)
            assert other.nrejected == 0 and other.nstored == at.held(f, radius).sum()
            assert other.copies(f) == at.held(f, radius).sum() / f.n
    elif seam == "net":  # the upload guard's count: every row up to reach (the net is
        assert whole.copies(f) == wide / f.n  # not known ahead)
    else:  # both: fewer than either alone
        for alone in ({"dense_after": None}, {"seam_spacing": None}):
            other = AtlasField(Atlas.from_dict({**at.to_dict(), **alone}), 1)
            other.add(f, val)
            assert other.nstored > whole.nstored, alone


def test_a_net_leaves_a_stored_sample_near_every_sample_it_drops():
    """What the net of a chart's outer seam promises: every flat in the chart's domain
    that it did not store has a stored sample within ``seam_spacing`` (divided by the
    chart's scale) in the chart's coordinates, and no two stored flats beyond
    ``dense_reach`` are that close (the stored ones before it did not cover it);
    any scale stores the same rows."""
    rng = np.random.default_rng(43)
    f = random_flats(rng, 1500, 2, 4, 1.0)
    val = np.cos(f.quadrics()[1][:, :1])
    counts = []
    for scale in (1.0, 0.05):
        at = Atlas.covering(2, 4, scale=scale, unit=DEFAULT_UNIT)  # the net as built
        fld = AtlasField(at, 1)
        fld.add(f, val)
        counts.append([g.nsamples for g in fld.fields])
        ro = at.route(f, at.reach)
        for c in range(0, at.ncharts, 7):
            rows = ro.rows[c]
            x = at.chart_field(c).chart(f.take(rows)).points
            held = fld.fields[c].points
            radius = at.seam_spacing / scale
            dist = np.sqrt(((x[:, None, :] - held[None]) ** 2).sum(axis=-1))
            assert (dist.min(axis=1) <= radius).all()  # stored (0) or covered
            beyond = np.degrees(ro.angles[c] - ro.nearest_angle[rows]) > at.dense_reach
            outer = x[beyond & (dist.min(axis=1) == 0)]
            gaps = np.sqrt(((outer[:, None] - outer[None]) ** 2).sum(axis=-1))
            assert (gaps[~np.eye(len(outer), dtype=bool)] > radius).all()
    assert counts[0] == counts[1]


def test_a_fitted_unit_is_tried_without_the_net():
    """``fitted_unit`` on an atlas with a net of its outer seam scores its units on
    fields without it (the net, in the charts' coordinates, would thin more in a
    longer unit): the same units and scores as on the atlas without the net."""
    from flatserve.atlas_field import fitted_unit

    rng = np.random.default_rng(44)
    f = random_flats(rng, 700, 2, 4, 1.0)
    val = np.sin(2 * f.quadrics()[1][:, 0]) + f.quadrics()[0][:, 0, 1]
    at = Atlas.covering(2, 4, dense_reach=7.0, seam_spacing=0.5, inner=2.0, trusted=6.0,
                        reach=14.0, relative=True)
    plain = Atlas.covering(2, 4, inner=2.0, trusted=6.0, reach=14.0, relative=True)
    got, want = (fitted_unit(a, f, val, factors=(0.5, 2.0), max_rows=700) for a in (at, plain))
    assert got.unit == want.unit
    np.testing.assert_array_equal(got.errors, want.errors)
    # (a field with the net in a unit would store other samples: the net is not idle here)
    nets = [AtlasField(at.with_unit(u), 1) for u in got.candidates[:2]]
    for n in nets:
        n.add(f, val)
    assert nets[0].nstored != nets[1].nstored


def test_a_thinner_seam_is_checked_and_kept():
    """dense_reach with dense_after, seam_spacing or both, a relative atlas only,
    trusted < dense_reach <= reach, a count, a distance; kept by to_dict, with_unit
    (without the net on request) and describe; defaults for planes in R^4 only, and
    not with radii given."""
    at = Atlas.covering(2, 4)
    assert (at.dense_reach, at.dense_after, at.seam_spacing) == (7.0, None, 1.0)
    back = Atlas.from_dict(at.to_dict())
    assert (back.dense_reach, back.dense_after, back.seam_spacing) == (7.0, None, 1.0)
    assert at.with_unit(2.0).seam_spacing == 1.0
    plain = at.with_unit(2.0, net=False)
    assert (plain.dense_reach, plain.dense_after, plain.seam_spacing) == (None, None, None)
    both = Atlas.from_dict({**at.to_dict(), "dense_after": 25})
    assert (both.with_unit(2.0, net=False).dense_reach, both.dense_after) == (7.0, 25)
    desc = Atlas.describe_spec(at.to_dict())["atlas"]
    assert (desc["dense_reach"], desc["dense_after"], desc["seam_spacing"]) == (7.0, None, 1.0)
    assert Atlas.covering(1, 4).dense_reach is None
    assert Atlas.covering(2, 4, reach=12).dense_reach is None
    assert Atlas.covering(2, 4, relative=False).dense_reach is None
    assert Atlas.covering(2, 4, relative=False).ncharts != at.ncharts  # its own cover
    described = Atlas.describe_spec(Atlas.covering(1, 4).to_dict())["atlas"]
    assert (described["dense_reach"], described["seam_spacing"]) == (None, None)
    spec = at.to_dict()
    for change, name, words in (
            ({"relative": False}, "dense_reach", "only a relative atlas"),
            ({"seam_spacing": None}, "dense_after", "dense_after or seam_spacing"),
            ({"dense_reach": None}, "dense_reach", "expected with seam_spacing"),
            ({"dense_reach": None, "seam_spacing": None, "dense_after": 3}, "dense_reach",
             "expected with dense_after"),
            ({"dense_reach": 6.0}, "dense_reach", "trusted < dense_reach <= reach"),
            ({"dense_reach": 15.0}, "dense_reach", "trusted < dense_reach <= reach"),
            ({"dense_reach": True}, "dense_reach", "an angle in degrees"),
            ({"inner": True}, "inner", "an angle in degrees"),
            ({"dense_after": -1}, "dense_after", "an integer >= 0"),
            ({"dense_after": True}, "dense_after", "an integer >= 0"),
            ({"dense_after": 2.5}, "dense_after", "an integer >= 0"),
            ({"seam_spacing": 0}, "seam_spacing", "finite, > 0"),
            ({"seam_spacing": -1.0}, "seam_spacing", "finite"),
            ({"seam_spacing": float("nan")}, "seam_spacing", "finite"),
            ({"seam_spacing": float("inf")}, "seam_spacing", "finite"),
            ({"seam_spacing": 10**400}, "seam_spacing", "finite"),
            ({"seam_spacing": True}, "seam_spacing", "finite"),
            ({"seam_spacing": "1"}, "seam_spacing", "finite")):
        with pytest.raises(InvalidInputError, match=words) as err:
            Atlas.from_dict({**spec, **change})
        assert err.value.argument == name, (change, err.value.argument)
    with pytest.raises(InvalidInputError, match="dense_reach"):
        Atlas.covering(1, 3, dense_reach=20, dense_after=5)
    with pytest.raises(InvalidInputError, match="seam_spacing"):
        Atlas.covering(1, 3, seam_spacing=1.0)


def test_a_relative_field_file_answers_the_same(tmp_path):
    rng = np.random.default_rng(34)
    field = AtlasField(Atlas.covering(1, 4, relative=True), channels=1)
    f = random_flats(rng, 1500, 1, 4, 1.0)
    field.add(f, np.sin(f.quadrics()[1][:, 0]))
    path = tmp_path / "rel.flatfield"
    field.save(path)
    back = AtlasField.load(path)
    assert back.atlas.relative
    q = random_flats(rng, 500, 1, 4, 1.0)
    a, b = field.query(q), back.query(q)
    assert np.isfinite(a.values).mean() > 0.5
    np.testing.assert_array_equal(a.values, b.values)


# ------------------------------------------------------------------ fitted unit
def test_a_fitted_unit_follows_what_the_values_change_with():
    """Values that change with the turn of a line only get a unit longer than the
    geometry's (``data_unit``), values that change with its shift only no longer
    one (a longer unit is clearly worse for them, a shorter one within the
    margin); and the fitted unit interpolates fresh queries better than the geometry's
    unit (held-out validation chose it from the samples alone)."""
    from flatserve.atlas_field import fitted_unit

    rng = np.random.default_rng(41)
    o, v = random_rays(rng, 2500)
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    r = o - np.einsum("ni,ni->n", a, o)[:, None] * a
    f = Flats.from_rays(o, v)
    at = Atlas.covering(1, 3)
    turn = fitted_unit(at, f, np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1]))  # (a line's: even)
    shift = fitted_unit(at, f, np.sin(3 * r[:, 0]) + r[:, 1] ** 2)
    geometry = data_unit(f, None)
    for fit in (turn, shift):  # the geometry's unit is among the candidates
        assert np.isclose(fit.candidates, geometry, rtol=0.3).any()
    assert turn.unit > 2 * geometry and shift.unit <= geometry, (turn, shift)
    assert shift.errors[shift.candidates > 3 * geometry].min() > 1.3 * shift.errors.min()
    chosen = list(turn.candidates).index(turn.unit)  # within the margin of the least
    assert turn.compared > 400 and turn.errors[chosen] <= 1.05 * turn.errors.min()
    assert (turn.errors[:chosen] > 1.05 * turn.errors.min()).all()  # the nearest such
    # fresh queries: the fitted unit against the geometry's
    qo, qv = random_rays(rng, 2000, R=0.8)
    qa = qv / np.linalg.norm(qv, axis=1, keepdims=True)
    want = np.cos(3 * qa[:, 0]) * np.cos(2 * qa[:, 1])
    errs = []
    for u in (turn.unit, geometry):
        fld = AtlasField(at.with_unit(float(u)), channels=1)
        fld.add(f, np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1]))
        got = fld.query(Flats.from_rays(qo, qv))
        errs.append(np.abs(got.values[:, 0] - want))
    both = np.isfinite(errs[0]) & np.isfinite(errs[1])
    assert np.median(errs[0][both]) < np.median(errs[1][both])


def test_a_fitted_unit_refuses_what_it_cannot_fit():
    from flatserve.atlas_field import fitted_unit

    rng = np.random.default_rng(42)
    f = Flats.from_rays(*random_rays(rng, 200))
    at = Atlas.covering(1, 3)
    for kw, name in (({"holdout": 1.0}, "holdout"), ({"factors": [1, -2]}, "factors"),
                     ({"max_rows": 20}, "flats")):
        with pytest.raises(InvalidInputError, match=name):
            fitted_unit(at, f, np.ones(200), **kw)
    with pytest.raises(InvalidInputError, match="values"):
        fitted_unit(at, f, np.r_[np.ones(199), np.nan])
    with pytest.raises(InvalidInputError, match=r"values: expected shape \(200,\)"):
        fitted_unit(at, f, np.ones((2, 200)))


def test_a_fitted_unit_keeps_the_geometrys_when_held_out_errors_cannot_tell():
    """Values the fit cannot tell apart (constant: every candidate exact to
    round-off; or a margin wider than any difference) keep ``data_unit`` of all
    the rows; a
    margin of 0 takes the least error however small the difference."""
    from flatserve.atlas_field import fitted_unit

    rng = np.random.default_rng(43)
    o, v = random_rays(rng, 1200)
    f, at = Flats.from_rays(o, v), Atlas.covering(1, 3)
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    turn = np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1])
    for metric in ("rmse", "median"):
        flat = fitted_unit(at, f, np.full(1200, 0.5), metric=metric)
        assert (flat.errors < 1e-12).all() and flat.unit == data_unit(f, np.full(1200, 0.5))
    wide = fitted_unit(at, f, turn, margin=0.99)
    assert wide.unit == data_unit(f, None)
    sharp = fitted_unit(at, f, turn, margin=0.0)
    assert sharp.errors.min() == sharp.errors[list(sharp.candidates).index(sharp.unit)]
    assert sharp.unit > 2 * data_unit(f, None)
    for kw, name in (({"margin": 1.0}, "margin"), ({"metric": "mae"}, "metric")):
        with pytest.raises(InvalidInputError, match=name):
            fitted_unit(at, f, turn, **kw)


def test_a_field_whose_unit_is_fit_takes_it_from_its_first_batch():
    """``Atlas(unit="fit")``: the first batch's :func:`fitted_unit` (of the atlas in
    any unit: it is replaced), stored and described as ``fit``; a later batch keeps
    it, a saved field loads with it; a first batch too small to fit takes
    ``data_unit``; any other word is refused naming ``unit``."""
    from flatserve.atlas_field import FIT_MIN_ROWS, choose_unit, fitted_unit

    rng = np.random.default_rng(44)
    o, v = random_rays(rng, 1600)
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    val = (np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1]))[:, None]
    f = Flats.from_rays(o, v)
    first, second = f.take(np.arange(1200)), f.take(np.arange(1200, 1600))
    want = fitted_unit(Atlas.covering(1, 3), first, val[:1200]).unit
    assert want > 2 * data_unit(first, val[:1200])  # (a fit that differs from the geometry's)
    at = Atlas.covering(1, 3, unit="fit")
    assert at.unit_from_data and at.unit_rule == "fit"
    assert Atlas.describe_spec(at.to_dict())["atlas"]["unit_from"] == "fit"
    assert Atlas.from_dict(at.to_dict()).unit_rule == "fit"
    fld = AtlasField(at, channels=1)
    fld.add(first, val[:1200])
    assert fld.atlas.unit == want == choose_unit(at, first, val[:1200])
    fld.add(second, val[1200:])
    assert fld.atlas.unit == want
    got = fld.describe()["atlas"]
    assert got["unit"] == want and got["unit_from"] == "fit"
    back = AtlasField.from_bytes(fld.to_bytes())
    q = Flats.from_rays(*random_rays(rng, 300, R=0.8))
    np.testing.assert_array_equal(back.query(q).values, fld.query(q).values)
    assert back.describe()["atlas"]["unit_from"] == "fit"
    small = f.take(np.arange(FIT_MIN_ROWS - 1))
    assert choose_unit(at, small, val[:FIT_MIN_ROWS - 1]) == data_unit(small, None)
    with pytest.raises(InvalidInputError, match="unit"):
        Atlas.covering(1, 3, unit="fitted")


def test_a_fitted_unit_steps_beyond_its_grid_while_the_least_score_is_at_an_end(monkeypatch):
    """The grid is extended from the least score, not from the unit the margin
    keeps: scores that fall slowly toward short units (each step 3 %, within the
    5 % margin of its neighbour) are followed 3 steps past the grid's end, and
    the choice is then the unit nearest the geometry's within the margin."""
    import types

    import flatserve.atlas_field as af

    rng = np.random.default_rng(45)
    f = Flats.from_rays(*random_rays(rng, 400))
    vals = np.zeros(400)
    base = data_unit(f, vals)

    class Scored:  # a field whose every answer is off by a function of its unit
        def __init__(self, atlas, channels):
            self.u = atlas.unit

        def add(self, flats, values):
            pass

        def query(self, flats):
            return types.SimpleNamespace(
                values=np.full((flats.n, 1), 1.0 + 0.03 * math.log2(self.u / base)))

    monkeypatch.setattr(af, "AtlasField", Scored)
    fit = af.fitted_unit(Atlas.covering(1, 3), f, vals)
    assert np.isclose(fit.candidates.min(), base / 32)  # 1/4, then 1/8, 1/16, 1/32
    assert np.isclose(fit.unit, base / 16)  # (0.88 within 5 % of 0.85, nearer the geometry)


def test_an_atlas_for_samples_takes_a_unit_rule():
    """``Atlas.for_samples(unit="fit")`` (the scales chosen in the default unit
    until the rule chooses); another word is refused naming ``unit``."""
    rng = np.random.default_rng(46)
    f = Flats.from_rays(*random_rays(rng, 300))
    at = Atlas.for_samples(f, unit="fit")
    assert at.unit_from_data and at.unit_rule == "fit" and at.unit == DEFAULT_UNIT
    with pytest.raises(InvalidInputError, match="unit"):
        Atlas.for_samples(f, unit="fitted")
