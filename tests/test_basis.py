"""Bases of flats (Sec. 3) and the tangent-space simplex (Sec. 5.1)."""
import numpy as np
import pytest
import scipy.linalg

from flatserve import flats
from flatserve.basis import (DEFAULT_VARIANT, S4, Basis, select_scale, simplex_vertices,
                             tangent_directions)
from flatserve.coordinates import OK, SINGULAR, coordinates
from flatserve.errors import BasisError, InvalidInputError

KD = [(1, 2), (1, 3), (2, 3), (1, 4), (2, 4), (2, 5), (3, 6)]


def random_center(rng, d, k):
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    A, N = q[:, :k], q[:, k:]
    alpha = rng.normal(size=d - k)
    return A, N, alpha


def flat_of_params(A, N, alpha, theta, beta):
    """The manifold map: rotate the frame by exp(sum theta_ij (n_j a_i^T - a_i n_j^T)),
    shift the offset coordinates by beta.  Returns (Q, r) flattened."""
    d, k = A.shape
    G = np.zeros((d, d))
    for i in range(k):
        for j in range(d - k):
            G += theta[i, j] * (np.outer(N[:, j], A[:, i]) - np.outer(A[:, i], N[:, j]))
    R = scipy.linalg.expm(G)
    RA, RN = R @ A, R @ N
    Q = np.eye(d) - RA @ RA.T
    r = RN @ (alpha + beta)
    return np.concatenate([Q.ravel(), r])


@pytest.mark.parametrize("k,d", KD)
def test_tangent_variant_is_tangent_by_finite_differences(k, d):
    rng = np.random.default_rng(10 * d + k)
    A, N, alpha = random_center(rng, d, k)
    dQ, dr = tangent_directions(A, N, alpha, "tangent")
    dQp, drp = tangent_directions(A, N, alpha, "paper")
    h = 1e-6
    idx = 0
    worst_paper = 0.0
    for i in range(k):
        for j in range(d - k):
            th = np.zeros((k, d - k))
            th[i, j] = h
            fd = (flat_of_params(A, N, alpha, th, 0) - flat_of_params(A, N, alpha, -th, 0)) / (2 * h)
            np.testing.assert_allclose(np.concatenate([dQ[idx].ravel(), dr[idx]]), fd, atol=1e-7)
            worst_paper = max(worst_paper, np.abs(
                np.concatenate([dQp[idx].ravel(), drp[idx]]) - fd).max())
            idx += 1
    for j in range(d - k):
        be = np.zeros(d - k)
        be[j] = h
        fd = (flat_of_params(A, N, alpha, np.zeros((k, d - k)), be)
              - flat_of_params(A, N, alpha, np.zeros((k, d - k)), -be)) / (2 * h)
        np.testing.assert_allclose(np.concatenate([dQ[idx].ravel(), dr[idx]]), fd, atol=1e-7)
        idx += 1
    assert idx == (k + 1) * (d - k)
    # Eq. 14 as printed (+ a a^T) is not a derivative of the manifold map
    assert worst_paper > 0.5


def test_simplex_vertices():
    np.testing.assert_array_equal(simplex_vertices(4), S4)
    for D in (1, 2, 3, 4, 6, 9, 12):
        S = simplex_vertices(D)
        assert S.shape == (D, D + 1)
        np.testing.assert_allclose(S.sum(1), 0, atol=1e-12)
        e = np.linalg.norm(S[:, :, None] - S[:, None, :], axis=0)
        np.testing.assert_allclose(e[~np.eye(D + 1, dtype=bool)], np.sqrt(8), rtol=1e-12)


@pytest.mark.parametrize("k,d", KD)
@pytest.mark.parametrize("variant", ["tangent", "paper"])
def test_tangent_simplex_structure(k, d, variant):
    rng = np.random.default_rng(d + 7 * k)
    A, N, alpha = random_center(rng, d, k)
    cQ, cr = N @ N.T, N @ alpha
    B = Basis.tangent_simplex(cQ, cr, k, scale=0.01, variant=variant, frames=(A, N))
    assert (B.m, B.k, B.d, B.dim) == ((k + 1) * (d - k) + 1, k, d, (k + 1) * (d - k))
    # centred: the barycentre is the centre flat
    np.testing.assert_allclose(B.Q.mean(0), cQ, atol=1e-14)
    np.testing.assert_allclose(B.r.mean(0), cr, atol=1e-14)
    rep = B.check()
    assert rep.ok, rep.failures
    # the centre's coordinates are the barycentre; combinations round-trip
    w = rng.random((50, B.m)) * 2 - 0.5
    w /= w.sum(1, keepdims=True)
    p = B.combine(w)
    c = B.coordinates(p.Q, p.r)
    assert (c.status == OK).all()
    np.testing.assert_allclose(c.weights, w, atol=1e-7)


def ray_setup(rng, n):
    scr = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    eye = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-4.5, -1.5, n)]
    return eye, scr - eye


def test_default_variant_keeps_more_rays_and_tangent_chart_is_the_45_degree_cone():
    rng = np.random.default_rng(0)
    o, v = ray_setup(rng, 20000)
    Q, r = flats.from_rays(o, v)
    fail = {}
    for variant in ("tangent", "paper"):
        c = Basis.around_axis(2, scale=0.01, variant=variant).coordinates(Q, r)
        fail[variant] = c.status != OK
    assert fail[DEFAULT_VARIANT].mean() == min(f.mean() for f in fail.values())
    assert fail["paper"].mean() > 2 * fail["tangent"].mean()
    cos = np.abs(v[:, 2]) / np.linalg.norm(v, axis=1)
    clear = np.abs(cos - np.sqrt(0.5)) > 1e-3  # away from the 45-degree boundary
    np.testing.assert_array_equal(fail["tangent"][clear], cos[clear] < np.sqrt(0.5))


def test_around_axis_frames():
    B = Basis.around_axis(axis=1, scale=0.02)  # the paper's Sec. 5.2 line along y
    a = np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(B.Q.mean(0), np.eye(3) - np.outer(a, a), atol=1e-15)
    assert B.scale == 0.02 and B.variant == DEFAULT_VARIANT
    with pytest.raises(InvalidInputError) as e:
        Basis.around_axis(axis=3)
    assert e.value.argument == "axis"
    with pytest.raises(InvalidInputError) as e:
        Basis.around_axis(scale=-1.0)
    assert e.value.argument == "scale"
    with pytest.raises(InvalidInputError) as e:
        Basis.around_axis(variant="other")
    assert e.value.argument == "variant"


def test_check_reports_orthogonal_pair_count_and_singularity():
    # Fig. 4: x-axis and y-axis are orthogonal
    Q, r = flats.from_rays([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]],
                           [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    rep = Basis(Q, r, 1).check()
    assert (0, 1) in rep.orthogonal_pairs and not rep.ok
    with pytest.raises(BasisError, match="orthogonal"):
        rep.raise_for_failures()
    # wrong count
    rep = Basis(Q[[0, 2]], r[[0, 2]], 1).check()
    assert not rep.count_ok and any("count" in f for f in rep.failures)
    # duplicate element -> singular coordinate system
    Q, r = flats.from_rays([[0.0, 0.0], [0.0, 1.0], [0.0, 1.0]],
                           [[1.0, 0.0], [1.0, 0.3], [1.0, 0.3]])
    rep = Basis(Q, r, 1).check()
    assert any("singular" in f for f in rep.failures)
    # a good basis passes
    Q, r = flats.from_rays([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]],
                           [[1.0, 0.0], [1.0, 0.3], [1.0, -0.2]])
    assert Basis(Q, r, 1).check().ok


@pytest.mark.parametrize("variant", ["tangent", "paper"])
def test_check_fails_a_collapsed_tangent_simplex_as_coordinates_do(variant):
    """check() agrees with coordinates(): a simplex collapsed to its centre
    (scale 1e-300) is well conditioned at the barycentre but charts nothing
    around it; a usable small scale passes and charts the paper's rays."""
    rng = np.random.default_rng(5)
    o, v = ray_setup(rng, 200)
    Q, r = flats.from_rays(o, v)
    for scale, usable in ((1e-300, False), (1e-100, False), (1e-3, True), (0.05, True)):
        B = Basis.around_axis(2, scale=scale, variant=variant)
        singular = np.asarray(B.coordinates(Q, r).status) == SINGULAR
        assert B.check().ok == usable
        assert singular.all() if not usable else not singular.any()


def test_basis_rejects_bad_input():
    with pytest.raises(InvalidInputError) as e:
        Basis(np.ones((2, 3, 3)) + np.arange(3), np.zeros((2, 3)), 1)
    assert e.value.argument == "Q"
    with pytest.raises(InvalidInputError) as e:
        Basis(np.eye(3)[None], np.zeros((1, 3)), 3)
    assert e.value.argument == "k"
    with pytest.raises(InvalidInputError) as e:
        Basis(np.eye(3)[None], np.zeros((2, 3)), 1)
    assert e.value.argument == "r"


def test_basis_coordinates_matches_function():
    rng = np.random.default_rng(1)
    B = Basis.around_axis(2, scale=0.05)
    o, v = ray_setup(rng, 500)
    Q, r = flats.from_rays(o, v)
    a = B.coordinates(Q, r)
    b = coordinates(B.Q, B.r, 1, Q, r)
    np.testing.assert_array_equal(a.weights, b.weights)
    c = B.coordinates_rays(o, v)
    np.testing.assert_array_equal(c.status, a.status)


def test_select_scale_bisection():
    rng = np.random.default_rng(3)
    o, v = ray_setup(rng, 2000)
    Q, r = flats.from_rays(o, v)
    make = lambda s: Basis.around_axis(2, scale=s)
    sel = select_scale(Q, r, make, fraction=0.9, lo=1e-3, hi=100.0, rtol=0.01)
    assert sel.reached and sel.coverage >= 0.9
    assert sel.basis.scale == sel.scale

    def cov(s):
        c = make(s).coordinates(Q, r)
        return np.mean((c.status == OK) & (c.weights.min(1) >= 0))

    assert cov(sel.scale) == sel.coverage
    assert cov(sel.scale / 1.03) < 0.9  # smallest up to the bisection tolerance
    # unreachable fraction: the 45-degree cone loses ~1.8 % of the rays at any scale
    sel = select_scale(Q, r, make, fraction=1.0, lo=1e-3, hi=100.0)
    assert not sel.reached and sel.scale == 100.0 and sel.coverage < 1.0
    # affine coverage does not depend on the scale (same affine hull): lo is returned
    sel = select_scale(Q, r, make, fraction=0.95, lo=1e-3, hi=1.0, inside="affine")
    assert sel.reached and sel.scale == 1e-3
