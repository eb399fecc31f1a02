"""The gradient interpolant (flatserve.gradient, ``query(interpolant="gradient")``),
checked against a second implementation of another kind (scipy's Delaunay cells,
neighbours by sorting every distance, one least-squares solve per sample), against
exact answers (affine values, the samples themselves), against the linear
interpolant's error on a smooth function, and tiled against whole."""
import numpy as np
import pytest
from scipy.spatial import Delaunay

import flatserve
from flatserve import Atlas, AtlasField, Basis, Field, Flats
from flatserve.errors import InvalidInputError
from flatserve.gradient import (GRADIENT_CHUNK_BYTES, gradient_chunk, neighbours_for, slopes,
                                taylor_blend)
from tests.harness.fig11 import fig11_rays


def _points_field(P, V):
    d = P.shape[1]
    field = Field(Basis.tangent_simplex(np.eye(d), np.zeros(d), 0), channels=V.shape[1])
    assert field.add(Flats.from_points(P), V).accepted == len(P)
    return field


def _reference(P, V, q):
    """Σ w_i T_i(x) over scipy's Delaunay cell, T_i(x) = f_i + g_i·(x − x_i) limited to
    the range of f_i and its neighbours' values widened to the linear answer; each g_i one
    weighted least-squares solve over the 3D+2 nearest samples found by sorting all
    distances."""
    n, D = P.shape
    K = 3 * D + 2
    G = np.empty((n, V.shape[1], D))
    lo, hi = np.empty_like(V), np.empty_like(V)
    for i in range(n):
        dist = np.linalg.norm(P - P[i], axis=1)
        nb = np.argsort(dist)[1:K + 1]
        w = 1.0 / dist[nb]
        G[i] = np.linalg.lstsq((P[nb] - P[i]) * w[:, None],
                               (V[nb] - V[i]) * w[:, None], rcond=None)[0].T
        lo[i], hi[i] = V[np.r_[i, nb]].min(axis=0), V[np.r_[i, nb]].max(axis=0)
    tri = Delaunay(P)
    s = tri.find_simplex(q)
    out = np.full((len(q), V.shape[1]), np.nan)
    for j in np.flatnonzero(s >= 0):
        T = tri.transform[s[j]]
        b = T[:D] @ (q[j] - T[D])
        lam = np.r_[b, 1 - b.sum()]
        ids = tri.simplices[s[j]]
        lin = lam @ V[ids]
        out[j] = sum(lam[a] * np.clip(V[i] + G[i] @ (q[j] - P[i]), np.minimum(lo[i], lin),
                                      np.maximum(hi[i], lin))
                     for a, i in enumerate(ids))
    return out


@pytest.mark.parametrize("d", [2, 3])
def test_a_points_field_answers_as_a_second_implementation(d):
    rng = np.random.default_rng(40 + d)
    P = rng.uniform(-1, 1, (300, d))
    V = np.c_[np.sin(3 * P.sum(axis=1)), P[:, 0] ** 2 - P[:, -1]]
    q = rng.uniform(-1.1, 1.1, (400, d))
    ref = _reference(P, V, q)
    inside = ~np.isnan(ref).any(axis=1)
    assert 0 < inside.sum() < len(q)
    out = _points_field(P, V).query(Flats.from_points(q), interpolant="gradient")
    np.testing.assert_array_equal(out.inside, inside)
    np.testing.assert_allclose(out.values[inside], ref[inside], rtol=0, atol=1e-9)
    assert np.isnan(out.values[~inside]).all()
    # and it is not the linear answer
    lin = _points_field(P, V).query(Flats.from_points(q)).values
    assert np.abs(lin[inside] - ref[inside]).max() > 1e-3


def test_slopes_of_affine_values_are_exact_in_every_channel():
    rng = np.random.default_rng(5)
    from scipy.spatial import cKDTree

    for D in (2, 4, 6):
        X = rng.normal(size=(200, D))
        M = rng.normal(size=(D, 3))
        V = X @ M + rng.normal(size=3)
        ids = rng.choice(200, 30, replace=False)
        s = slopes(cKDTree(X), X, V, ids)
        assert s.slope.shape == (30, 3, D) and s.low.shape == s.high.shape == (30, 3)
        np.testing.assert_allclose(s.slope, np.broadcast_to(M.T, s.slope.shape), atol=1e-9)
        assert (s.low <= V[ids]).all() and (V[ids] <= s.high).all()
        # few samples: finite slopes; where they do not span D directions, none (0)
        # and an empty range (the linear term)
        s = slopes(cKDTree(X[:3]), X[:3], V[:3], np.arange(3))
        assert np.isfinite(s.slope).all()
        if D > 2:
            assert (s.slope == 0).all() and (s.low > s.high).all()


def test_taylor_blend_with_exact_slopes_is_exact_for_affine_values():
    rng = np.random.default_rng(6)
    D, q = 3, 20
    M, c = rng.normal(size=(D, 2)), rng.normal(size=2)
    xv = rng.normal(size=(q, D + 1, D))
    w = rng.dirichlet(np.ones(D + 1), q)
    xq = np.einsum("qj,qjd->qd", w, xv)
    got = taylor_blend(xv, xv @ M + c, np.broadcast_to(M.T, (q, D + 1, 2, D)), w, xq)
    np.testing.assert_allclose(got, xq @ M + c, atol=1e-12)


def test_samples_and_affine_functions_of_the_chart_come_back():
    """At a sample every weight but its own is 0; an affine function of the chart's
    coordinates has exact slopes, so the blend is exact everywhere inside."""
    basis = Basis.around_axis(axis=2, scale=0.01)
    rng = np.random.default_rng(7)
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (3000, 3))
    dirs = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)] - eyes
    field = Field(basis, channels=2)
    ch = field.chart(Flats.from_rays(eyes, dirs))
    eyes, dirs, x = eyes[ch.ok], dirs[ch.ok], ch.points
    c = rng.normal(size=(x.shape[1], 2))
    field.add(Flats.from_rays(eyes, dirs), x @ c + [0.5, -1.0])
    back = field.query(Flats.from_rays(eyes[:500], dirs[:500]), interpolant="gradient")
    np.testing.assert_allclose(back.values, x[:500] @ c + [0.5, -1.0], atol=1e-8)
    qe = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (1000, 3))
    qd = np.c_[rng.uniform(-1, 1, (1000, 2)), np.zeros(1000)] - qe
    ch = field.chart(Flats.from_rays(qe, qd))
    qe, qd, xq = qe[ch.ok], qd[ch.ok], ch.points
    out = field.query(Flats.from_rays(qe, qd), interpolant="gradient")
    assert out.inside.sum() > 500
    np.testing.assert_allclose(out.values[out.inside], (xq @ c + [0.5, -1.0])[out.inside],
                               atol=1e-8)


def _smooth(A, c):
    P = np.einsum("ndk,nek->nde", A, A)
    return np.sin(2 * P[:, 0, 1] + P[:, 2, 2]) + np.cos(c @ [1.0, -0.5, 0.8])


def test_an_atlas_field_is_closer_to_a_smooth_function():
    """Planes in R^3: every chart's answer corrected by slopes; the median error
    against the truth falls below the linear interpolant's, the same queries
    answered (the interpolant changes values, not cells)."""
    from flatserve.grassmann import haar_frames

    rng = np.random.default_rng(8)

    def flats(n):
        A = haar_frames(n, 3, 2, rng)
        p = rng.uniform(-1, 1, (n, 3))
        return A, p - np.einsum("ndk,nek,ne->nd", A, A, p)

    A, c = flats(3000)
    Aq, cq = flats(1000)
    field = AtlasField(Atlas.covering(2, 3), channels=1)
    field.add(Flats.from_parametric(A, c), _smooth(A, c)[:, None])
    truth = _smooth(Aq, cq)
    lin = field.query(Flats.from_parametric(Aq, cq))
    grad = field.query(Flats.from_parametric(Aq, cq), interpolant="gradient")
    np.testing.assert_array_equal(lin.inside, grad.inside)
    np.testing.assert_array_equal(lin.status, grad.status)
    ins = lin.inside
    assert ins.mean() > 0.9
    e_lin = np.median(np.abs(lin.values[ins, 0] - truth[ins]))
    e_grad = np.median(np.abs(grad.values[ins, 0] - truth[ins]))
    assert e_grad < 0.9 * e_lin, (e_grad, e_lin)
    # at the samples: their values
    back = field.query(Flats.from_parametric(A[:200], c[:200]), interpolant="gradient")
    np.testing.assert_allclose(back.values[:, 0], _smooth(A[:200], c[:200]), atol=1e-9)


def test_outside_the_hull_keeps_the_linear_answer():
    rng = np.random.default_rng(9)
    P = rng.uniform(-1, 1, (200, 2))
    V = np.sin(3 * P)
    q = rng.uniform(-1.3, 1.3, (300, 2))
    field = _points_field(P, V)
    for outside in ("nan", "clamp"):
        lin = field.query(Flats.from_points(q), outside=outside)
        grad = field.query(Flats.from_points(q), outside=outside, interpolant="gradient")
        out = ~lin.inside
        assert out.any()
        np.testing.assert_array_equal(grad.values[out], lin.values[out])
        assert not np.allclose(grad.values[~out], lin.values[~out])


def test_a_tiled_chart_answers_as_the_whole_one():
    o, d, v = fig11_rays(60, seed=2)
    rng = np.random.default_rng(10)
    pick = rng.choice(len(o), 300, replace=False)
    qf = Flats.from_rays(o[pick] + rng.normal(0, 0.01, (300, 3)), d[pick])
    basis = Basis.around_axis(axis=2, scale=0.01)
    whole, tiled = Field(basis, channels=1), Field(basis, channels=1, tiles=2)
    for f in (whole, tiled):
        f.add(Flats.from_rays(o, d), v)
    ref = whole.query(qf, interpolant="gradient")
    got = tiled.query(qf, interpolant="gradient")
    assert ref.inside.mean() > 0.5
    np.testing.assert_array_equal(got.inside, ref.inside)
    # the same bits: the terms are summed in the order of the vertices' ids, not in
    # the order a tile lists its cell's vertices
    np.testing.assert_array_equal(got.values, ref.values)
    back = Field.from_bytes(tiled.to_bytes())
    np.testing.assert_array_equal(back.query(qf, interpolant="gradient").values, ref.values)


def test_a_field_grown_between_queries_uses_its_new_samples():
    rng = np.random.default_rng(11)
    P = rng.uniform(-1, 1, (400, 2))
    V = np.sin(3 * P[:, :1]) * P[:, 1:]
    q = rng.uniform(-0.8, 0.8, (200, 2))
    grown = _points_field(P[:200], V[:200])
    grown.query(Flats.from_points(q), interpolant="gradient")  # a neighbour tree of 200
    grown.add(Flats.from_points(P[200:]), V[200:])
    fresh = _points_field(P, V)
    np.testing.assert_allclose(  # (the same cells, built in another order)
        grown.query(Flats.from_points(q), interpolant="gradient").values,
        fresh.query(Flats.from_points(q), interpolant="gradient").values, rtol=0, atol=1e-12)


def test_bad_choices_name_the_argument():
    field = _points_field(np.random.default_rng(1).uniform(size=(10, 2)), np.ones((10, 1)))
    with pytest.raises(InvalidInputError, match="interpolant: expected 'linear' or 'gradient'"):
        field.query(Flats.from_points(np.zeros((1, 2))), interpolant="cubic")
    with pytest.raises(InvalidInputError, match="interpolant"):
        AtlasField(Atlas.covering(0, 2), 1).query(Flats.from_points(np.zeros((1, 2))),
                                                  interpolant="cubic")
    with pytest.raises(InvalidInputError, match="neighbours: an integer of at least"):
        neighbours_for(6, 3)
    assert neighbours_for(6) == 20 and neighbours_for(6, 6) == 6
    assert flatserve.options.Interpolant("gradient") == "gradient"


def test_values_that_jump_are_not_overshot():
    """A step across a line (an edge in an image): slopes fitted across it would carry a
    vertex's value past its neighbours' (shown with the terms unlimited); limited, every
    answer stays within the values 0 and 1, and away from the step it is the linear one."""
    rng = np.random.default_rng(12)
    P = rng.uniform(-1, 1, (600, 2))
    V = (P[:, :1] + 0.3 * P[:, 1:] > 0).astype(float)
    q = rng.uniform(-0.9, 0.9, (3000, 2))
    field = _points_field(P, V)
    out = field.query(Flats.from_points(q), interpolant="gradient", return_weights=True)
    ins = out.inside
    assert ins.mean() > 0.9
    assert out.values[ins].min() >= 0.0 and out.values[ins].max() <= 1.0
    # unlimited, the same slopes overshoot
    from scipy.spatial import cKDTree

    ids, w = out.ids[ins], out.weights[ins]
    used, at = np.unique(ids, return_inverse=True)
    s = slopes(cKDTree(field.points), field.points, field.values, used)
    g = s.slope[at.reshape(ids.shape)]
    free = taylor_blend(field.points[ids], field.values[ids], g, w, q[ins])
    assert free.min() < -0.05 and free.max() > 1.05
    # where every vertex's neighbourhood is on one side, the answer is its constant
    far = np.abs(q[:, 0] + 0.3 * q[:, 1]) > 0.4
    np.testing.assert_allclose(out.values[ins & far, 0], (q[ins & far, 0] + 0.3 * q[ins & far, 1] > 0),
                               atol=1e-12)


def test_without_scipy_the_gradient_interpolant_says_what_to_install(monkeypatch):
    """The library needs NumPy only: without SciPy a linear query answers and a gradient
    one names the extra that brings it."""
    import sys

    field = _points_field(np.random.default_rng(13).uniform(size=(20, 2)), np.ones((20, 1)))
    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails
    q = Flats.from_points(np.full((1, 2), 0.5))
    assert field.query(q).values.shape == (1, 1)
    with pytest.raises(ImportError, match=r"flatserve\[gradient\]"):
        field.query(q, interpolant="gradient")


def test_neighbours_on_a_line_give_no_slope_across_it():
    """60 samples on y = 0 and 6 off it, f = x + 2y: a vertex whose nearest samples all
    lie on the line cannot see the slope across it; its term is the linear answer, so
    the affine function is still exact."""
    rng = np.random.default_rng(14)
    P = np.r_[np.c_[np.linspace(-1, 1, 60), np.zeros(60)], rng.uniform(-1, 1, (6, 2))]
    V = (P @ [1.0, 2.0])[:, None]
    q = rng.uniform(-0.5, 0.5, (400, 2))
    out = _points_field(P, V).query(Flats.from_points(q), interpolant="gradient")
    assert out.inside.sum() > 100
    np.testing.assert_allclose(out.values[out.inside, 0], q[out.inside] @ [1.0, 2.0], atol=1e-12)


def test_new_values_of_the_same_samples_are_seen():
    """Samples given again with other values (no new point): the next gradient query
    uses the new values and their slopes, not the last query's."""
    rng = np.random.default_rng(15)
    P = rng.uniform(-1, 1, (300, 2))
    q = rng.uniform(-0.7, 0.7, (200, 2))
    field = _points_field(P, np.sin(3 * P[:, :1]))
    field.query(Flats.from_points(q), interpolant="gradient")
    field.add(Flats.from_points(P), np.cos(2 * P[:, 1:]))  # duplicates: values replaced
    assert field.nsamples == 300
    fresh = _points_field(P, np.cos(2 * P[:, 1:]))
    np.testing.assert_allclose(
        field.query(Flats.from_points(q), interpolant="gradient").values,
        fresh.query(Flats.from_points(q), interpolant="gradient").values, rtol=0, atol=1e-12)


@pytest.mark.parametrize("tiles", [1, 2])
def test_an_insert_waits_for_the_slopes_of_a_query(tiles, monkeypatch):
    """The cells, the neighbours and the values of a gradient answer are one state of
    the chart: an insert started while the slopes are computed waits for them (they run
    under the query's read lock), and the answer is the state before it."""
    import threading

    rng = np.random.default_rng(16)
    o, d, v = fig11_rays(40, seed=3)
    basis = Basis.around_axis(axis=2, scale=0.01)
    field = Field(basis, channels=1, tiles=tiles)
    field.add(Flats.from_rays(o[:1000], d[:1000]), v[:1000])
    before = Field(basis, channels=1)
    before.add(Flats.from_rays(o[:1000], d[:1000]), v[:1000])
    pick = rng.choice(1000, 100, replace=False)
    qf = Flats.from_rays(o[pick] + rng.normal(0, 0.01, (100, 3)), d[pick])
    taylor = Field._taylor
    seen = {}

    def racing(self, *a):
        if self is field and "insert" not in seen:
            seen["insert"] = threading.Thread(
                target=lambda: field.add(Flats.from_rays(o[1000:], d[1000:]), v[1000:]))
            seen["insert"].start()
            seen["insert"].join(0.5)
            seen["waited"] = seen["insert"].is_alive()
        return taylor(self, *a)

    monkeypatch.setattr(Field, "_taylor", racing)
    got = field.query(qf, interpolant="gradient")
    seen["insert"].join()
    assert seen["waited"]
    assert field.nsamples > before.nsamples
    want = before.query(qf, interpolant="gradient")
    assert want.inside.mean() > 0.5
    np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-9)


def test_values_near_the_float_range_give_finite_answers_inside():
    """A slope fitted across values near the float range overflows: that vertex keeps
    the linear term, and the answer stays finite (not a missing value taken for
    "outside the hull")."""
    g = np.linspace(-1, 1, 9)
    P = np.r_[np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), [[1e-8, 0.0]]]
    V = np.zeros((len(P), 1))
    V[-1] = 1e300
    field = _points_field(P, V)
    q = Flats.from_points(np.array([[0.1, 0.05], [0.1, 0.1], [0.6, 0.6], [-0.3, 0.2]]))
    with np.errstate(all="raise"):  # and no warning either
        got = field.query(q, interpolant="gradient")
    lin = field.query(q)
    assert got.inside.all() and np.isfinite(got.values).all()
    assert (got.values >= 0).all() and (got.values <= 1e300).all()
    np.testing.assert_array_equal(got.values[2:], lin.values[2:])  # far from it: 0
    V[-1] = -1.7e308  # and with differences that overflow too
    got = _points_field(P, V).query(q, interpolant="gradient")
    assert got.inside.all() and np.isfinite(got.values).all()
    # a channel that overflows keeps its slopes out of the others': a smooth second
    # channel is answered as it is alone
    W = np.c_[V[:, 0], np.sin(2 * P[:, 0]) + P[:, 1]]
    both = _points_field(P, W).query(q, interpolant="gradient").values
    alone = _points_field(P, W[:, 1:]).query(q, interpolant="gradient").values
    np.testing.assert_allclose(both[:, 1], alone[:, 0], rtol=1e-12, atol=0)
    assert np.abs(alone - _points_field(P, W[:, 1:]).query(q).values).max() > 1e-6


def test_a_large_batch_is_answered_in_chunks_of_bounded_memory(monkeypatch):
    import tracemalloc

    import flatserve.field as field_module

    rng = np.random.default_rng(11)
    P = rng.uniform(-1, 1, (400, 3))
    V = np.sin(P @ rng.normal(size=(3, 64)))  # 64 channels
    field = _points_field(P, V)
    X = rng.uniform(-0.9, 0.9, (20_000, 3))
    q = Flats.from_points(X)
    field.query(Flats.from_points(X[:10]), interpolant="gradient")  # the k-d tree, built once
    tracemalloc.start()
    try:
        got = field.query(q, interpolant="gradient")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    answer = got.values.nbytes  # 10 MB; unchunked, the slopes took 60 times as much
    assert got.inside.mean() > 0.9
    assert peak < 3 * answer + 2 * GRADIENT_CHUNK_BYTES, (peak, answer)
    assert gradient_chunk(3, 64) < 20_000  # (so it was answered in chunks)
    # and chunks do not change the bits
    monkeypatch.setattr(field_module, "gradient_chunk", lambda *a, **k: 7)
    np.testing.assert_array_equal(field.query(Flats.from_points(X[:2000]),
                                              interpolant="gradient").values,
                                  got.values[:2000])
