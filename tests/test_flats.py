"""Flats as (Q, r): constructors, back-conversions, validation, projection (Sec. 2)."""
import numpy as np
import pytest
import scipy.linalg

from flatserve import flats
from flatserve.errors import InvalidFlatError, InvalidInputError, WeightsError

DK = [(1, 0), (2, 0), (2, 1), (3, 0), (3, 1), (3, 2), (4, 1), (4, 2), (5, 2), (6, 3)]


def projector(A):
    """Orthogonal projector onto span(A) via the normal equations (independent oracle)."""
    return A @ np.linalg.solve(np.swapaxes(A, 1, 2) @ A, np.swapaxes(A, 1, 2))


def nearest_on_flat(A, b, x):
    """Closest point of {A y + b} to x by least squares, row by row."""
    out = np.empty_like(x)
    for i in range(len(x)):
        if A.shape[2] == 0:
            out[i] = b[i]
            continue
        y, *_ = np.linalg.lstsq(A[i], x[i] - b[i], rcond=None)
        out[i] = A[i] @ y + b[i]
    return out


@pytest.mark.parametrize("d,k", DK)
def test_from_parametric_roundtrip(d, k):
    rng = np.random.default_rng(100 * d + k)
    n = 50
    A = rng.normal(size=(n, d, k))  # not orthonormal
    b = rng.normal(size=(n, d))
    Q, r = flats.from_parametric(A, b)
    flats.validate(Q, r, k)
    np.testing.assert_allclose(Q, np.eye(d) - projector(A) if k else np.eye(d)[None].repeat(n, 0),
                               atol=1e-10)
    A2, b2 = flats.to_parametric(Q, r, k)
    np.testing.assert_allclose(np.swapaxes(A2, 1, 2) @ A2, np.eye(k)[None].repeat(n, 0), atol=1e-10)
    if k:
        np.testing.assert_allclose(projector(A2), projector(A), atol=1e-9)
    # b2 is the closest point of the flat to the origin
    np.testing.assert_allclose(b2, nearest_on_flat(A, b, np.zeros_like(b)), atol=1e-9)


@pytest.mark.parametrize("d,k", DK)
def test_from_points_contains_points(d, k):
    rng = np.random.default_rng(7 + d * 10 + k)
    P = rng.uniform(-2, 2, size=(40, k + 1, d))
    Q, r = flats.from_points(P)
    flats.validate(Q, r, k)
    for i in range(k + 1):
        assert np.all(flats.squared_distance(Q, r, P[:, i]) < 1e-20 + 1e-12)


@pytest.mark.parametrize("d,k", [dk for dk in DK if dk[1] < dk[0]])
def test_from_normal_roundtrip(d, k):
    rng = np.random.default_rng(3 + d * 10 + k)
    n = 40
    N = rng.normal(size=(n, d, d - k))
    c = rng.normal(size=(n, d - k))
    Q, r = flats.from_normal(N, c)
    flats.validate(Q, r, k)
    # a solution of N^T x = c (least-norm, by an independent routine) lies on the flat
    x0 = np.stack([np.linalg.lstsq(N[i].T, c[i], rcond=None)[0] for i in range(n)])
    assert np.all(flats.squared_distance(Q, r, x0) < 1e-18)
    np.testing.assert_allclose(r, x0, atol=1e-10)  # least-norm solution = closest point
    N2, c2 = flats.to_normal(Q, r, k)
    np.testing.assert_allclose(N2 @ np.swapaxes(N2, 1, 2), Q, atol=1e-10)
    np.testing.assert_allclose(np.einsum("nij,ni->nj", N2, x0), c2, atol=1e-10)
    Q3, r3 = flats.from_normal(N2, c2)
    np.testing.assert_allclose(Q3, Q, atol=1e-10)
    np.testing.assert_allclose(r3, r, atol=1e-10)


@pytest.mark.parametrize("d", [2, 3, 5])
def test_from_rays_roundtrip(d):
    rng = np.random.default_rng(d)
    o = rng.normal(size=(30, d))
    v = rng.normal(size=(30, d)) * rng.uniform(0.1, 10, size=(30, 1))
    Q, r = flats.from_rays(o, v)
    flats.validate(Q, r, 1)
    A, b = flats.to_parametric(Q, r, 1)
    a = v / np.linalg.norm(v, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", A[:, :, 0], a)), 1.0, atol=1e-12)
    assert np.all(flats.squared_distance(Q, r, o) < 1e-24 + 1e-20)
    assert np.all(flats.squared_distance(Q, r, o + 3.0 * v) < 1e-18)
    np.testing.assert_allclose(flats.closest_point(Q, r), nearest_on_flat(v[:, :, None], o, 0 * o),
                               atol=1e-10)
    Q2, r2 = flats.from_parametric(A, b)
    np.testing.assert_allclose(Q2, Q, atol=1e-12)
    np.testing.assert_allclose(r2, r, atol=1e-12)


def test_squared_distance_matches_least_squares():
    rng = np.random.default_rng(11)
    A = rng.normal(size=(25, 4, 2))
    b = rng.normal(size=(25, 4))
    x = rng.normal(size=(25, 4)) * 3
    Q, r = flats.from_parametric(A, b)
    ref = ((x - nearest_on_flat(A, b, x)) ** 2).sum(axis=1)
    np.testing.assert_allclose(flats.squared_distance(Q, r, x), ref, rtol=1e-10, atol=1e-12)
    # the paper's expanded form (Eq. 2) agrees
    eq2 = np.einsum("ni,nij,nj->n", x, Q, x) - 2 * np.einsum("ni,ni->n", r, x) + (r * r).sum(1)
    np.testing.assert_allclose(flats.squared_distance(Q, r, x), eq2, rtol=1e-9, atol=1e-10)


class TestValidate:
    def setup_method(self):
        rng = np.random.default_rng(5)
        self.Q, self.r = flats.from_parametric(rng.normal(size=(6, 3, 1)), rng.normal(size=(6, 3)))

    def test_valid(self):
        flats.validate(self.Q, self.r, 1)

    @pytest.mark.parametrize("kind,cond,arg", [
        ("asym", "(C1) symmetric", "Q"),
        ("scale", "(C1) idempotent", "Q"),
        ("rank", "(C1) rank", "Q"),
        ("offset", "(C2)", "r"),
    ])
    def test_violations_name_condition_and_rows(self, kind, cond, arg):
        Q, r = self.Q.copy(), self.r.copy()
        rows = [1, 4]
        if kind == "asym":
            Q[rows, 0, 1] += 1e-3
        elif kind == "scale":
            Q[rows] *= 1.5
        elif kind == "rank":
            Q[rows] = np.eye(3)  # a point (k = 0), not a line
        else:
            A, _ = flats.to_parametric(Q, r, 1)
            r[rows] += A[rows, :, 0]
        with pytest.raises(InvalidFlatError) as e:
            flats.validate(Q, r, 1)
        assert cond in str(e.value) and "[1, 4]" in str(e.value)
        assert e.value.argument == arg


def test_projection_of_a_flat_is_itself():
    rng = np.random.default_rng(2)
    for d, k in DK:
        Q, r = flats.from_parametric(rng.normal(size=(10, d, k)), rng.normal(size=(10, d)))
        p = flats.project(Q, r, k)
        np.testing.assert_allclose(p.Q, Q, atol=1e-12)
        np.testing.assert_allclose(p.r, r, atol=1e-12)
        assert not p.ambiguous.any()


def test_projection_matches_definition():
    """Sec. 2.3 against scipy's eigh and an explicit solve of Q* x = r*."""
    rng = np.random.default_rng(9)
    d, k, m, n = 4, 2, 3, 20
    Qb, rb = flats.from_parametric(rng.normal(size=(m, d, k)), rng.normal(size=(m, d)))
    w = rng.random((n, m))
    w /= w.sum(1, keepdims=True)
    p = flats.affine_combination(w, Qb, rb, k)
    flats.validate(p.Q, p.r, k)
    for i in range(n):
        Qs = np.tensordot(w[i], Qb, 1)
        rs = w[i] @ rb
        lam, V = scipy.linalg.eigh(Qs)
        Nn = V[:, k:]
        np.testing.assert_allclose(p.Q[i], Nn @ Nn.T, atol=1e-10)
        np.testing.assert_allclose(p.r[i], Nn @ Nn.T @ np.linalg.solve(Qs, rs), atol=1e-9)
        np.testing.assert_allclose(p.gap[i], lam[k] - lam[k - 1], atol=1e-12)


def test_fig3_parallel_lines_interpolate_distance_linearly():
    """Fig. 3 (right): two parallel lines; the distance to L1 is linear in the weight."""
    rng = np.random.default_rng(3)
    for d in (2, 3):
        v = rng.normal(size=(1, d))
        o = rng.normal(size=(2, d))
        Q, r = flats.from_rays(o, np.repeat(v, 2, 0))
        t = np.linspace(-0.5, 1.5, 21)
        p = flats.affine_combination(np.c_[1 - t, t], Q, r, 1)
        np.testing.assert_allclose(p.Q, np.repeat(Q[:1], 21, 0), atol=1e-12)  # stays parallel
        dist = np.linalg.norm(p.r - r[0], axis=1)
        np.testing.assert_allclose(dist, np.abs(t) * np.linalg.norm(r[1] - r[0]), atol=1e-12)


def test_fig3_orthogonal_lines_midpoint_is_ambiguous():
    """Sec. 3.1 / Fig. 4: the midpoint of two orthogonal lines has no unique projection."""
    Q, r = flats.from_rays([[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.0], [0.0, 1.0]])
    p = flats.affine_combination([[0.5, 0.5], [0.3, 0.7]], Q, r, 1)
    assert p.ambiguous.tolist() == [True, False]
    assert p.gap[0] < flats.GAP_TOL


def test_weights_must_sum_to_one():
    Q, r = flats.from_rays([[0.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [1.0, 0.1]])
    with pytest.raises(WeightsError) as e:
        flats.affine_combination([[0.5, 0.5], [0.6, 0.6]], Q, r, 1)
    assert e.value.argument == "weights" and "[1]" in str(e.value)
    assert isinstance(e.value, ValueError)
    # huge opposite weights cannot be checked to sum to one; overflowing sums neither
    for w in ([[1e17, -1e17]], [[1e308, 1e308]]):
        with pytest.raises(WeightsError):
            flats.affine_combination(w, Q, r, 1)
    # moderately large affine weights that do sum to one pass (relative tolerance)
    flats.affine_combination([[1e4 + 1.0, -1e4]], Q, r, 1)


@pytest.mark.parametrize("call,arg", [
    (lambda: flats.from_parametric([[[np.nan], [1.0]]], [[0.0, 0.0]]), "A"),
    (lambda: flats.from_parametric([[[1.0], [1.0]]], [[0.0, np.inf]]), "b"),
    (lambda: flats.from_parametric([[[1.0, 2.0], [1.0, 2.0]]], [[0.0, 0.0]]), "A"),  # k >= d
    (lambda: flats.from_parametric([[[1.0, 2.0], [2.0, 4.0], [0, 0]]], [[0.0, 0.0, 0]]), "A"),
    (lambda: flats.from_parametric(np.zeros((1, 3, 1)), np.zeros((1, 3))), "A"),
    (lambda: flats.from_parametric(np.ones((2, 3, 1)), np.zeros((3, 3))), "b"),
    (lambda: flats.from_rays([[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]]), "directions"),
    (lambda: flats.from_rays([[0.0, 0.0, np.nan]], [[0.0, 0.0, 1.0]]), "origins"),
    (lambda: flats.from_rays([[0.0, 0.0]], [[0.0, 0.0, 1.0]]), "directions"),
    (lambda: flats.from_rays([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]), "origins"),
    (lambda: flats.from_points([[[0.0, 0.0], [0.0, 0.0]]]), "points"),
    (lambda: flats.from_points(np.zeros((1, 3, 2))), "points"),  # k = 2 = d
    (lambda: flats.from_normal([[[1.0], [0.0]]], [[1.0, 2.0]]), "c"),
    (lambda: flats.from_normal(np.zeros((1, 2, 1)), [[1.0]]), "N"),
    (lambda: flats.validate(np.eye(3)[None], np.zeros((1, 3)), 3), "k"),
    (lambda: flats.project(np.eye(3)[None], np.zeros((1, 3)), -1), "k"),
    (lambda: flats.project(np.eye(3)[None], np.zeros((1, 2)), 1), "rs"),
    (lambda: flats.squared_distance(np.eye(3)[None], np.zeros((1, 3)), [[1.0, 2.0]]), "x"),
])
def test_bad_input_names_argument(call, arg):
    with pytest.raises(ValueError) as e:
        call()
    assert isinstance(e.value, InvalidInputError)
    assert e.value.argument == arg
    assert str(e.value).startswith(arg + ":")


@pytest.mark.parametrize("d", [1, 2, 3, 5])
def test_points_form_is_the_parametric_form_with_no_spanning_vectors(d):
    """``Flats.from_points`` (n, d): the same flats as A (n, d, 0) + b and Q = I + r,
    by name through ``from_arrays`` (inferred or given), arrays read-only."""
    P = np.random.default_rng(d).uniform(-2, 2, (7, d))
    f = flats.Flats.from_points(P)
    assert (f.form, f.k, f.d, len(f), f.shapes) == ("points", 0, d, 7, {"points": (7, d)})
    Q, r = f.quadrics()
    Qp, rp = flats.Flats.from_parametric(np.zeros((7, d, 0)), P).quadrics()
    np.testing.assert_array_equal(Q, Qp)
    np.testing.assert_array_equal(r, rp)
    flats.validate(Q, r, 0)
    assert not f.arrays["points"].flags.writeable and not Q.flags.writeable
    for form in (None, "points"):
        g = flats.Flats.from_arrays({"points": P.tolist()}, k=0, d=d, form=form)
        assert g.form == "points"
        np.testing.assert_array_equal(g.arrays["points"], P)
    assert flats.infer_form({"points": P}) == "points"
    assert flats.form_shapes("points", 0, d) == {"points": ("n", d)}
    np.testing.assert_array_equal(f.take([2, 0]).arrays["points"], P[[2, 0]])


@pytest.mark.parametrize("call,arg,words", [
    # points are k = 0 only: the message names the flats asked for
    (lambda: flats.Flats.from_arrays({"points": np.zeros((2, 3))}, k=1, d=3), "form",
     "1-flats in R^3 (k = 1, d = 3)"),
    (lambda: flats.form_shapes("points", 2, 4), "form", "2-flats in R^4 (k = 2, d = 4)"),
    (lambda: flats.Flats.from_arrays({"points": np.zeros((2, 4))}, k=0, d=3), "points",
     "expected shape (n, 3), got (2, 4)"),
    (lambda: flats.Flats.from_arrays({"points": [[0.0, np.nan]]}, k=0, d=2), "points", "NaN"),
    (lambda: flats.Flats.from_arrays({"points": []}, k=0, d=2, min_rows=1), "points",
     "at least one row"),
    (lambda: flats.Flats.from_points(np.zeros((2, 0))), "points", "d >= 1"),
    (lambda: flats.Flats.from_points(np.zeros((2, 2, 1))), "points", "expected shape"),
    (lambda: flats.infer_form({"points": 1, "Q": 1}), "body", "points"),
    (lambda: flats.Flats.from_arrays({}, k=0, d=2), "body", "points (k = 0)"),
])
def test_points_form_errors_name_the_field_and_shape(call, arg, words):
    with pytest.raises(InvalidInputError) as e:
        call()
    assert e.value.argument == arg and str(e.value).startswith(arg + ":"), str(e.value)
    assert words in str(e.value), str(e.value)
