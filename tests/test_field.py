"""Field = basis + triangulation + values, checked with oracles:
sample rays come back exactly, affine functions of the chart are reproduced,
non-round-tripping rays are rejected with reasons, snapshots round-trip."""
import numpy as np
import pytest

import flatserve
from flatserve import Basis, Field
from flatserve.coordinates import NO_SAMPLES, OK
from flatserve.embedding import embed


def paper_rays(rng, n):
    """The paper's set-up: screen z=0 in [-1,1]^2, eyes in [-1,1]^2 x [-4.5,-1.5]."""
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


@pytest.fixture(scope="module")
def basis():
    return Basis.around_axis(axis=2, scale=0.01)


def test_sample_rays_come_back_exactly(basis):
    rng = np.random.default_rng(1)
    o, dirs = paper_rays(rng, 3000)
    vals = rng.uniform(0, 1, (3000, 3))
    field = Field(basis, channels=3)
    res = field.add_rays(o, dirs, vals)
    assert res.accepted + res.rejected.size == 3000
    assert res.accepted > 2500
    accepted = np.setdiff1d(np.arange(3000), res.rejected)
    out = field.query_rays(o[accepted], dirs[accepted])
    assert out.inside.all()
    np.testing.assert_allclose(out.values, vals[accepted], atol=1e-9)


def test_affine_function_of_the_chart_is_reproduced(basis):
    """Piecewise-linear interpolation reproduces affine functions exactly."""
    rng = np.random.default_rng(2)
    o, dirs = paper_rays(rng, 4000)
    Q, r = flatserve.flats.from_rays(o, dirs)
    coords = basis.coordinates(Q, r)
    x = embed(coords.weights)
    c = rng.normal(size=(x.shape[1], 2))
    vals = x @ c + np.array([0.5, -1.0])
    field = Field(basis, channels=2)
    field.add(flatserve.Flats.from_quadrics(Q, r, 1), vals)

    qo, qd = paper_rays(rng, 2000)
    out = field.query_rays(qo, qd)
    Qq, rq = flatserve.flats.from_rays(qo, qd)
    cq = basis.coordinates(Qq, rq)
    expect = embed(cq.weights) @ c + np.array([0.5, -1.0])
    assert out.inside.sum() > 1000
    np.testing.assert_allclose(out.values[out.inside], expect[out.inside], atol=1e-8)
    assert np.isnan(out.values[~out.inside]).all()
    assert (out.status[out.inside] == OK).all()


def test_rays_outside_the_chart_are_rejected_with_reasons(basis):
    rng = np.random.default_rng(3)
    o, dirs = paper_rays(rng, 500)
    # Rays lying in the screen plane are far from the chart around the z-axis.
    bad_o = np.c_[rng.uniform(-1, 1, (20, 2)), np.zeros(20)]
    bad_d = np.c_[rng.normal(size=(20, 2)), np.zeros(20)]
    field = Field(basis)
    res = field.add_rays(np.r_[o, bad_o], np.r_[dirs, bad_d], rng.uniform(size=520))
    assert set(range(500, 520)) <= set(res.rejected.tolist())
    assert len(res.reasons) == res.rejected.size
    assert all("round-trip" in s or "singular" in s for s in res.reasons)
    assert field.nrejected == res.rejected.size
    assert field.nsamples == res.accepted - res.duplicates


def test_save_load_answers_identically(basis, tmp_path):
    rng = np.random.default_rng(4)
    o, dirs = paper_rays(rng, 2000)
    field = Field(basis, channels=1)
    field.add_rays(o, dirs, rng.uniform(size=2000))
    path = tmp_path / "f.field"
    field.save(path)
    again = Field.load(path)
    assert (again.nsamples, again.nsimplex, again.nrejected) == (field.nsamples, field.nsimplex, field.nrejected)
    qo, qd = paper_rays(rng, 1000)
    a, b = field.query_rays(qo, qd), again.query_rays(qo, qd)
    np.testing.assert_array_equal(a.inside, b.inside)
    np.testing.assert_array_equal(a.values, b.values)


def test_damaged_field_file_raises(basis, tmp_path):
    field = Field(basis)
    rng = np.random.default_rng(5)
    o, dirs = paper_rays(rng, 300)
    field.add_rays(o, dirs, rng.uniform(size=300))
    path = tmp_path / "f.field"
    field.save(path)
    data = path.read_bytes()
    (tmp_path / "t.field").write_bytes(data[: len(data) // 2])
    with pytest.raises(flatserve.errors.SnapshotError):
        Field.load(tmp_path / "t.field")
    (tmp_path / "m.field").write_bytes(b"garbage" + data[7:])
    with pytest.raises(flatserve.errors.SnapshotError):
        Field.load(tmp_path / "m.field")


def test_bad_input_names_the_argument(basis):
    field = Field(basis, channels=2)
    rng = np.random.default_rng(6)
    o, dirs = paper_rays(rng, 10)
    with pytest.raises(ValueError, match="values"):
        field.add_rays(o, dirs, np.ones((10, 3)))
    with pytest.raises(ValueError, match="origins|directions"):
        field.add_rays(o[:, :2], dirs, np.ones((10, 2)))
    with pytest.raises(ValueError, match="outside"):
        field.query_rays(o, dirs, outside="zero")
    bad = o.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="origins"):
        field.query_rays(bad, dirs)
    with pytest.raises(ValueError, match="channels"):
        Field(basis, channels=0)
    # points on a line: 1-dimensional charts, which no triangulation here takes; said
    # in the field's k, d (not the triangulation's ndim)
    with pytest.raises(ValueError, match=r"d: 0-flats in R\^1 make 1-dimensional charts") as e:
        Field(Basis.tangent_simplex(np.eye(1), np.zeros(1), 0), channels=1)
    assert e.value.argument == "d"


def test_deferred_prepare_validates_now_and_charts_later(basis):
    """prepare*(defer=True): bad input raises at once; the returned callable gives
    the batch prepare() would have given, for every input form."""
    from flatserve import flats
    from flatserve.errors import InvalidInputError

    rng = np.random.default_rng(4)
    o, v = paper_rays(rng, 400)
    v[::9, 2] = 0.0  # some rays outside the chart: rejected rows, not an error
    vals = rng.normal(size=(400, 2))
    field = Field(basis, channels=2)
    Q, r = flats.from_rays(o, v)
    A = v / np.linalg.norm(v, axis=1, keepdims=True)
    calls = [flats.Flats.from_rays(o, v), flats.Flats.from_quadrics(Q, r, 1),
             flats.Flats.from_parametric(A[:, :, None], o)]
    for batch in calls:
        now = field.prepare(batch, vals)
        later = field.prepare(batch, vals, defer=True)
        assert callable(later)
        got = later()
        assert got.rejected.size and got.reasons == now.reasons
        np.testing.assert_array_equal(got.rejected, now.rejected)
        np.testing.assert_array_equal(got.x, now.x)
        np.testing.assert_array_equal(got.values, now.values)
    bad = v.copy()
    bad[3] = 0.0
    with pytest.raises(InvalidInputError) as ei:
        field.prepare(flats.Flats.from_rays(o, bad), vals, defer=True)
    assert ei.value.argument == "directions"
    with pytest.raises(InvalidInputError) as ei:
        field.prepare(flats.Flats.from_rays(o, v), vals[:, :1], defer=True)
    assert ei.value.argument == "values"


def test_query_does_not_wait_when_asked_not_to(basis):
    """blocking=False: None at once while an insert holds the triangulation (an
    event loop must never wait); the same answer once it is free."""
    rng = np.random.default_rng(8)
    o, dirs = paper_rays(rng, 1000)
    field = Field(basis, channels=1)
    field.add_rays(o, dirs, rng.uniform(size=1000))
    q = flatserve.Flats.from_rays(o[:20], dirs[:20])
    with field.triangulation.lock.write():
        assert field.query(q, blocking=False) is None
    a, b = field.query(q, blocking=False, return_weights=True), field.query(q, return_weights=True)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.ids, b.ids)


def test_flats_are_not_changed_through_the_callers_arrays():
    rng = np.random.default_rng(9)
    o, dirs = paper_rays(rng, 10)
    f = flatserve.Flats.from_rays(o, dirs)
    o[0, 0] = np.nan  # the caller's array stays the caller's
    assert o.flags.writeable and np.isfinite(f.arrays["origins"]).all()
    A = dirs[:, :, None] / np.linalg.norm(dirs, axis=1)[:, None, None]
    p = flatserve.Flats.from_parametric(A, np.zeros_like(dirs))
    Q, _ = p.quadrics()
    with pytest.raises(ValueError):
        Q[0, 0, 0] = 5.0  # read-only


@pytest.mark.parametrize("d", [2, 3])
def test_points_field_answers_as_scipy_linear_nd_interpolator(d):
    """k = 0: a field of points (the service's default, a covering atlas of one chart, and
    a one-chart Field) answers as scipy's LinearNDInterpolator on the same points in
    general position, in the `points` form and in the (n, d, 0) parametric form."""
    from scipy.interpolate import LinearNDInterpolator

    from flatserve import Atlas, AtlasField
    from flatserve.contract import new_field

    rng = np.random.default_rng(30 + d)
    P = rng.uniform(-1, 1, (400, d))
    V = np.c_[np.sin(3 * P.sum(axis=1)), P[:, 0] ** 2]
    q = rng.uniform(-1.1, 1.1, (500, d))  # some outside the hull
    ref = LinearNDInterpolator(P, V)(q)
    inside = ~np.isnan(ref).any(axis=1)
    assert 0 < inside.sum() < len(q)
    forms = {"points": lambda X: flatserve.Flats.from_points(X),
             "parametric": lambda X: flatserve.Flats.from_parametric(np.zeros((len(X), d, 0)), X)}
    for make in (lambda: AtlasField(Atlas.covering(0, d), channels=2),
                 lambda: new_field(2, basis=Basis.tangent_simplex(np.eye(d), np.zeros(d), 0))):
        for name, of in forms.items():
            field = make()
            assert field.add(of(P), V).accepted == len(P), name
            out = field.query(of(q))
            np.testing.assert_array_equal(out.inside, inside)
            np.testing.assert_allclose(out.values[inside], ref[inside], rtol=0, atol=1e-12)
            assert np.isnan(out.values[~inside]).all()


def test_status_tells_an_empty_chart_from_an_unreachable_flat(basis):
    """NO_SAMPLES where the coordinates round-trip while the samples do not span a
    simplex (none, then too few); the chart's own status elsewhere; OK once they span."""
    rng = np.random.default_rng(11)
    o, dirs = paper_rays(rng, 400)
    far_o = np.c_[rng.uniform(-1, 1, (40, 2)), np.zeros(40)]  # in the screen plane:
    far_d = np.c_[rng.normal(size=(40, 2)), np.zeros(40)]     # outside the chart
    q = flatserve.Flats.from_rays(np.r_[o, far_o], np.r_[dirs, far_d])
    field = Field(basis)
    coords = field.chart(q).status
    assert (coords == OK).sum() > 300 and (coords[400:] != OK).all()

    def check(out, spans):
        assert out.status.dtype == np.int8
        want = np.where(coords == OK, OK if spans else NO_SAMPLES, coords)
        np.testing.assert_array_equal(out.status, want)
        if not spans:
            assert not out.inside.any() and np.isnan(out.values).all()

    for outside in ("nan", "clamp"):
        check(field.query(q, outside=outside), spans=False)   # empty
    # samples that do not span: D = 4 needs 5 affinely independent points
    s_o, s_d = paper_rays(rng, 2000)
    field.add_rays(s_o[:3], s_d[:3], rng.uniform(size=3))
    assert field.nsamples == 3
    check(field.query(q, outside="clamp"), spans=False)
    field.add_rays(s_o[3:], s_d[3:], rng.uniform(size=1997))
    out = field.query(q)
    check(out, spans=True)
    assert out.inside.any() and not out.inside[coords != OK].any()
