"""Coordinates of flats in a basis (Sec. 4, Fig. 8, Eq. 9 and 12; Fig. 9)."""
import numpy as np
import pytest

from flatserve import flats
from flatserve.basis import Basis
from flatserve.coordinates import (AMBIGUOUS, NOT_REPRESENTABLE, OK, ROUNDTRIP_TOL, SINGULAR,
                                   coordinates, coordinates_rays, system_matrix)
from flatserve.errors import InvalidFlatError, InvalidInputError


def random_basis(rng, d, k, m=None):
    m = (k + 1) * (d - k) + 1 if m is None else m
    return flats.from_points(rng.uniform(-1, 1, size=(m, k + 1, d)))


def convex_targets(rng, Qb, rb, k, n):
    w = rng.random((n, len(Qb)))
    w /= w.sum(1, keepdims=True)
    p = flats.affine_combination(w, Qb, rb, k)
    return w, p.Q, p.r


def loop_system(Qb, rb, A, N, rt):
    """Fig. 8 written out entry by entry (oracle for the batched einsum)."""
    n, d, k = A.shape
    m = len(Qb)
    M = np.zeros((n, (k + 1) * (d - k) + 1, m))
    for t in range(n):
        row = 0
        for i in range(k):
            for j in range(d - k):
                for l in range(m):
                    M[t, row, l] = N[t, :, j] @ Qb[l] @ A[t, :, i]
                row += 1
        for j in range(d - k):
            for l in range(m):
                M[t, row, l] = N[t, :, j] @ (Qb[l] @ rt[t] - rb[l])
            row += 1
        M[t, row, :] = 1.0
    return M


@pytest.mark.parametrize("d,k", [(2, 1), (3, 1), (4, 2), (5, 3)])
def test_system_matrix_matches_fig8(d, k):
    rng = np.random.default_rng(d * 10 + k)
    Qb, rb = random_basis(rng, d, k)
    _, Q, r = convex_targets(rng, Qb, rb, k, 7)
    A, N = flats.frames(Q, k)
    np.testing.assert_allclose(system_matrix(Qb, rb, A, N, r), loop_system(Qb, rb, A, N, r),
                               atol=1e-13)


@pytest.mark.parametrize("d,k", [(2, 1), (3, 1), (3, 2), (4, 1), (4, 2)])
def test_recovers_convex_weights(d, k):
    rng = np.random.default_rng(42 + d + k)
    Qb, rb = random_basis(rng, d, k)
    w, Q, r = convex_targets(rng, Qb, rb, k, 200)
    c = coordinates(Qb, rb, k, Q, r)
    assert (c.status == OK).all()
    np.testing.assert_allclose(c.weights, w, atol=1e-8)
    assert (c.residual < ROUNDTRIP_TOL).all()


def random_rotation(rng, d):
    q, rr = np.linalg.qr(rng.normal(size=(d, d)))
    return q * np.sign(np.diag(rr))


@pytest.mark.parametrize("d,k", [(2, 1), (3, 1), (3, 2), (4, 2)])
def test_rigid_motion_invariance(d, k):
    rng = np.random.default_rng(7 * d + k)
    Qb, rb = random_basis(rng, d, k)
    # targets: convex and affine combinations plus random flats (any status)
    w = rng.normal(size=(100, len(Qb))) * 0.6 + 0.2
    w /= w.sum(1, keepdims=True)
    p = flats.affine_combination(w, Qb, rb, k)
    Qr, rr = flats.from_parametric(rng.normal(size=(50, d, k)), rng.normal(size=(50, d)))
    Q = np.concatenate([p.Q, Qr])
    r = np.concatenate([p.r, rr])
    c0 = coordinates(Qb, rb, k, Q, r)
    R = random_rotation(rng, d)
    t = rng.normal(size=d) * 3

    def move(Q, r):
        Qm = R @ Q @ R.T
        return Qm, np.einsum("nij,nj->ni", Qm, r @ R.T + t)

    c1 = coordinates(*move(Qb, rb), k, *move(Q, r))
    ok = c0.status == OK
    assert ok.sum() >= 100  # all the combinations at least
    np.testing.assert_array_equal(c1.status[ok], OK)
    np.testing.assert_allclose(c1.weights[ok], c0.weights[ok], atol=1e-7)
    bad = ~ok
    np.testing.assert_array_equal(c1.status[bad] != OK, True)


def test_fig9_parallel_basis_nonparallel_target_not_representable():
    """Fig. 9 left/middle: a basis of two parallel lines only represents parallel lines."""
    rng = np.random.default_rng(9)
    for d in (2, 3):
        v = rng.normal(size=d)
        Qb, rb = flats.from_rays(rng.normal(size=(2, d)), np.stack([v, v]))
        # non-parallel targets: least squares gives some weights, status says so
        Qt, rt = flats.from_rays(rng.normal(size=(20, d)), rng.normal(size=(20, d)))
        c = coordinates(Qb, rb, 1, Qt, rt)
        assert (c.status == NOT_REPRESENTABLE).all()
        assert (c.residual > 1e-3).all()
        np.testing.assert_allclose(c.weights.sum(1), 1.0, atol=1e-9)
        # parallel targets in the hull: fewer elements than (k+1)(d-k)+1, still exact
        w = rng.random((20, 2))
        w /= w.sum(1, keepdims=True)
        p = flats.affine_combination(w, Qb, rb, 1)
        c = coordinates(Qb, rb, 1, p.Q, p.r)
        assert (c.status == OK).all()
        np.testing.assert_allclose(c.weights, w, atol=1e-9)


def test_more_elements_than_needed_round_trip_only():
    """Fig. 9 right: with more elements the weights are not unique (min-norm), yet round-trip."""
    rng = np.random.default_rng(4)
    Qb, rb = random_basis(rng, 2, 1, m=5)  # needs 3
    w, Q, r = convex_targets(rng, Qb, rb, 1, 100)
    c = coordinates(Qb, rb, 1, Q, r)
    assert (c.status == OK).mean() > 0.9
    ok = c.status == OK
    p = flats.affine_combination(c.weights[ok], Qb, rb, 1)
    np.testing.assert_allclose(p.Q, Q[ok], atol=1e-6)
    np.testing.assert_allclose(p.r, r[ok], atol=1e-6)
    assert np.abs(c.weights - w).max() > 1e-3  # not the weights used: underdetermined


def test_singular_system_reported():
    rng = np.random.default_rng(5)
    Qb, rb = random_basis(rng, 2, 1)
    Qb[2], rb[2] = Qb[1], rb[1]  # duplicate element: columns equal
    _, Q, r = convex_targets(rng, Qb[:2], rb[:2], 1, 10)
    c = coordinates(Qb, rb, 1, Q, r)
    assert (c.status == SINGULAR).all()


def test_ambiguous_recombination_reported():
    """Orthogonal lines (Sec. 3.1): the barycentre-like target maps to an ambiguous Q*."""
    Qb, rb = flats.from_rays([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]],
                             [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    # any target; force weights whose recombination is the orthogonal midpoint
    from flatserve.coordinates import roundtrip_residual
    res, amb = roundtrip_residual(np.array([[0.5, 0.5, 0.0]]), Qb, rb, 1, Qb[:1], rb[:1])
    assert amb[0]
    assert AMBIGUOUS == 3


def test_targets_are_validated():
    Qb, rb = flats.from_rays(np.zeros((3, 2)), [[1.0, 0.0], [1.0, 0.2], [1.0, -0.3]])
    with pytest.raises(InvalidFlatError):
        coordinates(Qb, rb, 1, 2 * Qb[:1], rb[:1])
    with pytest.raises(InvalidInputError) as e:
        coordinates(Qb, rb, 1, Qb[:1, :1, :1], rb[:1])
    assert e.value.argument == "Q"


def test_native_rays_kernel_is_built():
    # the extension is always built in this project: a missing kernel is a
    # stale/broken build and must fail loudly, never fall back silently
    from flatserve import _native
    from flatserve.coordinates import _fast_rays
    assert _native.coordinates_rays3 is not None
    assert callable(_fast_rays())


def test_missing_native_kernel_is_an_error(monkeypatch):
    from flatserve import _native
    monkeypatch.setattr(_native, "coordinates_rays3", None)
    B = Basis.around_axis(2, scale=0.01)
    with pytest.raises(RuntimeError, match="coordinates_rays3"):
        coordinates_rays(B.Q, B.r, np.zeros((1, 3)), [[0.0, 0.0, 1.0]])
    # the explicit reference path does not need it
    assert coordinates_rays(B.Q, B.r, np.zeros((1, 3)), [[0.0, 0.0, 1.0]], native=False).status[0] == OK


@pytest.mark.parametrize("n", [1, 7, 5000, 40001])
def test_native_rays_threads_bit_identical(n):
    rng = np.random.default_rng(12)
    B = Basis.around_axis(2, scale=0.01)
    eye = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-4.5, -1.5, n)]
    scr = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    v = scr - eye
    v[3::97] = rng.normal(size=v[3::97].shape)  # some rays far off the chart
    one = coordinates_rays(B.Q, B.r, eye, v, native=True, threads=1)
    assert set(np.unique(one.status)) >= {OK}
    for th in (None, 2, 3, 8, n + 5):
        got = coordinates_rays(B.Q, B.r, eye, v, native=True, threads=th)
        np.testing.assert_array_equal(got.status, one.status)
        assert got.weights.tobytes() == one.weights.tobytes()
        assert got.residual.tobytes() == one.residual.tobytes()
    got = B.coordinates_rays(eye, v, threads=3)
    assert got.weights.tobytes() == one.weights.tobytes()


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_native_rays_bad_threads(bad):
    B = Basis.around_axis(2)
    with pytest.raises(InvalidInputError) as e:
        coordinates_rays(B.Q, B.r, np.zeros((1, 3)), [[0.0, 0.0, 1.0]], threads=bad)
    assert e.value.argument == "threads"


@pytest.mark.parametrize("variant", ["tangent", "paper"])
def test_native_rays_path_matches_numpy_reference(variant):
    rng = np.random.default_rng(8)
    B = Basis.around_axis(2, scale=0.01, variant=variant)
    n = 20000
    eye = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-4.5, -1.5, n)]
    scr = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    ref = coordinates_rays(B.Q, B.r, eye, scr - eye, native=False)
    got = coordinates_rays(B.Q, B.r, eye, scr - eye, native=True)
    np.testing.assert_array_equal(got.status, ref.status)
    ok = ref.status == OK
    assert ok.mean() > 0.9
    np.testing.assert_allclose(got.weights[ok], ref.weights[ok], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(got.residual[ok], ref.residual[ok], atol=1e-9)  # both << tol
    # the reference itself equals the general path through (Q, r)
    Q, r = flats.from_rays(eye[:2000], (scr - eye)[:2000])
    gen = coordinates(B.Q, B.r, 1, Q, r, native=False)
    np.testing.assert_allclose(gen.weights, ref.weights[:2000], atol=1e-12)
    # (Q, r) targets take the native path too (direction recovered from I - Q)
    nat = coordinates(B.Q, B.r, 1, Q, r)
    np.testing.assert_array_equal(nat.status, gen.status)
    ok = gen.status == OK
    np.testing.assert_allclose(nat.weights[ok], gen.weights[ok], rtol=1e-8, atol=1e-8)


def test_native_rays_path_singular_and_edge_cases():
    Qb, rb = flats.from_rays(np.zeros((5, 3)), [[0, 0, 1.0], [0, 0.1, 1], [0.1, 0, 1],
                                                [0.1, 0.1, 1], [0.1, 0.1, 1]])  # duplicate
    o = np.array([[0.0, 0, 0], [0.1, 0.2, 0.3]])
    v = np.array([[0.0, 0, -1], [0.05, 0.02, 1]])  # a = -z exercises the ONB branch
    ref = coordinates_rays(Qb, rb, o, v, native=False)
    got = coordinates_rays(Qb, rb, o, v, native=True)
    np.testing.assert_array_equal(got.status, SINGULAR)
    np.testing.assert_array_equal(got.status, ref.status)
    B = Basis.around_axis(2, scale=0.01)
    got = coordinates_rays(B.Q, B.r, o, v, native=True)
    ref = coordinates_rays(B.Q, B.r, o, v, native=False)
    np.testing.assert_allclose(got.weights, ref.weights, atol=1e-9)
    np.testing.assert_array_equal(got.status, OK)


def test_rays_bad_input():
    B = Basis.around_axis(2)
    with pytest.raises(InvalidInputError) as e:
        coordinates_rays(B.Q, B.r, np.zeros((2, 3)), [[0, 0, 1.0], [0, 0, 0]])
    assert e.value.argument == "directions"
    with pytest.raises(InvalidInputError) as e:
        coordinates_rays(B.Q, B.r, np.zeros((2, 2)), np.ones((2, 2)))
    assert e.value.argument == "origins"
