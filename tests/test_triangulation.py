"""flatserve.Triangulation against scipy (an independent oracle) and invariants."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from flatserve import _native
from flatserve.errors import InvalidInputError, SnapshotError
from flatserve.triangulation import LocateKind, Triangulation, seam_net

scipy_spatial = pytest.importorskip("scipy.spatial")
scipy_interp = pytest.importorskip("scipy.interpolate")

VALUE_TOL = 1e-9          # issue 3: agreement with LinearNDInterpolator
WEIGHT_TOL = 1e-9         # weights >= -WEIGHT_TOL
RECON_TOL = 1e-9          # sum w_i p_i reproduces the query
CHUNK = int(_native.core.QUERY_CHUNK)

# points per dimension: enough cells to walk, small enough for scipy.
NPTS = {2: 1500, 3: 1000, 4: 600, 5: 250}


def _sample(rng, D, n, C=2):
    return rng.random((n, D)), rng.standard_normal((n, C))


def _queries(rng, D, q, margin=0.15):
    return rng.random((q, D)) * (1 + 2 * margin) - margin


def _filled(rng, D, n, C=2):
    """A triangulation of ``n`` random samples (C channels) inserted in one batch;
    (triangulation, points, values)."""
    P, V = _sample(rng, D, n, C)
    tri = Triangulation(D)
    tri.insert(P, V)
    return tri, P, V


def _assert_same_cells_and_values(a, b, q):
    """Same cells as vertex sets (the order of a cell's vertices may differ) and the
    same interpolated values at ``q``."""
    def cells(t):
        return {tuple(sorted(s)) for s in t.simplices.tolist()}

    assert cells(a) == cells(b)
    va, ia = a.interpolate(q)
    vb, ib = b.interpolate(q)
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_allclose(va[ia], vb[ib], atol=1e-12)


def _assert_matches_scipy(tri, P, V, q, rtol=0.0):
    """``tri`` interpolates like scipy's LinearNDInterpolator on the same samples:
    the same inside mask, values within VALUE_TOL; returns (values, inside)."""
    ours, inside = tri.interpolate(q)
    ref = scipy_interp.LinearNDInterpolator(P, V)(q)
    ref_inside = ~np.isnan(ref).any(axis=1)
    np.testing.assert_array_equal(inside, ref_inside)
    assert inside.any()
    np.testing.assert_allclose(ours[inside], ref[inside], rtol=rtol, atol=VALUE_TOL)
    return ours, inside


@pytest.mark.parametrize("D", [2, 3, 4, 5])
def test_interpolation_matches_scipy(D):
    rng = np.random.default_rng(100 + D)
    P, V = _sample(rng, D, NPTS[D])
    tri = Triangulation(D)
    res = tri.insert(P, V)
    assert res.n_new == len(P) and res.n_duplicates == 0
    np.testing.assert_array_equal(res.ids, np.arange(len(P)))
    q = _queries(rng, D, 4000)
    ours, inside = _assert_matches_scipy(tri, P, V, q)
    assert (~inside).any()
    assert np.isnan(ours[~inside]).all()


@pytest.mark.parametrize("D", [2, 3, 4])
def test_simplices_match_scipy_delaunay(D):
    rng = np.random.default_rng(200 + D)
    P, _ = _sample(rng, D, NPTS[D] // 2)
    tri = Triangulation(D)
    tri.insert(P)
    ours = {tuple(sorted(s)) for s in tri.simplices.tolist()}
    ref = {tuple(sorted(s)) for s in scipy_spatial.Delaunay(P).simplices.tolist()}
    assert ours == ref
    assert tri.nsimplex == len(ours)
    assert tri.is_valid()


@pytest.mark.parametrize("D", [2, 3, 4, 5])
def test_located_queries_lie_in_their_simplex(D):
    rng = np.random.default_rng(300 + D)
    tri, P, _ = _filled(rng, D, NPTS[D])
    q = _queries(rng, D, 3000)
    loc = tri.locate(q)
    ins = loc.inside
    w, ids = loc.weights[ins], loc.ids[ins]
    assert (ids >= 0).all()
    assert (w >= -WEIGHT_TOL).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    recon = np.einsum("qk,qkd->qd", w, tri.points[ids])
    np.testing.assert_allclose(recon, q[ins], atol=RECON_TOL)
    # find_simplex / barycentric agree with locate and with simplices
    s = tri.find_simplex(q)
    np.testing.assert_array_equal(s, loc.simplex)
    assert (s[~ins] == -1).all()
    np.testing.assert_array_equal(tri.simplices[s[ins]], ids)
    b = tri.barycentric(q)
    np.testing.assert_array_equal(b[ins], w)
    assert np.isnan(b[~ins]).all()
    # outside the hull: exactly one infinite vertex in the answer
    out = loc.kind == LocateKind.OUTSIDE_CONVEX_HULL
    np.testing.assert_array_equal(out, ~ins)
    assert ((loc.ids[out] == -1).sum(axis=1) == 1).all()
    # scipy agrees on which queries are inside
    ref = scipy_spatial.Delaunay(P).find_simplex(q) >= 0
    np.testing.assert_array_equal(ins, ref)


@pytest.mark.parametrize("order", ["hilbert", "given"])
def test_threads_give_identical_results(order):
    D = 4
    rng = np.random.default_rng(7)
    tri, _, _ = _filled(rng, D, 800, C=3)
    q = _queries(rng, D, 5 * CHUNK + 123)
    base = tri.locate(q, order=order, threads=1)
    v1, i1 = tri.interpolate(q, order=order, threads=1, outside="clamp")
    for th in (2, 3, 8):
        loc = tri.locate(q, order=order, threads=th)
        np.testing.assert_array_equal(loc.ids, base.ids)
        np.testing.assert_array_equal(loc.weights, base.weights)
        np.testing.assert_array_equal(loc.kind, base.kind)
        np.testing.assert_array_equal(loc.simplex, base.simplex)
        v, i = tri.interpolate(q, order=order, threads=th, outside="clamp")
        np.testing.assert_array_equal(v, v1)
        np.testing.assert_array_equal(i, i1)
    vd, _ = tri.interpolate(q)  # default threads
    np.testing.assert_allclose(vd[i1], v1[i1], atol=1e-12)


def test_orders_agree():
    D = 3
    rng = np.random.default_rng(8)
    tri, _, _ = _filled(rng, D, 700)
    q = _queries(rng, D, 2 * CHUNK + 5)
    a, ia = tri.interpolate(q, order="hilbert")
    b, ib = tri.interpolate(q, order="given")
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_allclose(a[ia], b[ib], atol=1e-12)


def test_leading_query_shape_and_single_point():
    rng = np.random.default_rng(9)
    tri, _, _ = _filled(rng, 2, 100)
    q = rng.random((4, 5, 2)) * 0.5 + 0.25
    v, ins = tri.interpolate(q)
    assert v.shape == (4, 5, 2) and ins.shape == (4, 5)
    v0, _ = tri.interpolate(q[1, 2])
    np.testing.assert_array_equal(v0, v[1, 2])
    assert tri.locate(q).weights.shape == (4, 5, 3)


def test_later_batches_equal_one_batch():
    D = 3
    rng = np.random.default_rng(10)
    one, P, V = _filled(rng, D, 900)
    parts = Triangulation(D)
    for lo, hi in [(0, 2), (2, 50), (50, 400), (400, 900)]:
        r = parts.insert(P[lo:hi], V[lo:hi])
        np.testing.assert_array_equal(r.ids, np.arange(lo, hi))
    assert parts.npoints == 900
    np.testing.assert_array_equal(parts.points, P)
    np.testing.assert_array_equal(parts.values, V)
    _assert_same_cells_and_values(one, parts, _queries(rng, D, 2000))
    assert parts.is_valid()


def test_duplicates_later_value_wins():
    D = 2
    rng = np.random.default_rng(11)
    tri, P, V = _filled(rng, D, 50, C=1)
    # batch: 3 new points, 2 repeats of old points, one new point repeated
    new = rng.random((3, D)) + 2.0
    batch = np.vstack([new[0], P[7], new[1], P[7], new[2], new[1], P[3]])
    bv = np.arange(7, dtype=float).reshape(-1, 1) + 100
    r = tri.insert(batch, bv)
    assert r.n_new == 3 and r.n_duplicates == 4
    np.testing.assert_array_equal(r.ids, [50, 7, 51, 7, 52, 51, 3])
    assert tri.npoints == 53 and tri.values.shape == (53, 1)
    np.testing.assert_array_equal(tri.points[50:], new)
    assert tri.values[7, 0] == 103      # last of the two rows for P[7]
    assert tri.values[51, 0] == 105     # last of the two rows for new[1]
    assert tri.values[3, 0] == 106
    assert tri.values[50, 0] == 100 and tri.values[52, 0] == 104
    np.testing.assert_array_equal(tri.values[:3], V[:3])
    # interpolating exactly at a duplicated vertex returns the new value
    v, ins = tri.interpolate(P[7])
    assert ins and v[0] == 103
    loc = tri.locate(P[7][None])
    assert loc.kind[0] == LocateKind.ON_VERTEX
    assert tri.is_valid()


def test_locate_kinds_on_faces():
    # 2D: a square split in two; query a vertex, an edge midpoint, the inside
    tri = Triangulation(2)
    pts = np.array([[0, 0], [1, 0], [0, 1], [1.1, 1.2]], float)
    tri.insert(pts, np.arange(4.0))
    q = np.array([[0, 0], [0.5, 0], [0.2, 0.2], [5, 5]], float)
    loc = tri.locate(q, order="given")
    assert loc.kind.tolist() == [LocateKind.ON_VERTEX, LocateKind.ON_FACET,
                                 LocateKind.IN_CELL, LocateKind.OUTSIDE_CONVEX_HULL]
    w0 = dict(zip(loc.ids[0].tolist(), loc.weights[0].tolist()))
    assert w0[0] == 1.0 and sum(w0.values()) == 1.0
    assert (loc.weights[1] == 0).sum() == 1
    # 3D: a point on an edge of a tetrahedron is ON_FACE
    tri3 = Triangulation(3)
    tri3.insert(np.vstack([np.eye(3), np.zeros(3)]))
    loc3 = tri3.locate([[0.5, 0.5, 0.0], [0.5, 0, 0]])
    assert loc3.kind.tolist() == [LocateKind.ON_FACE, LocateKind.ON_FACE]


def test_outside_policies():
    D = 3
    rng = np.random.default_rng(12)
    tri, _, V = _filled(rng, D, 400, C=2)
    q = _queries(rng, D, 3000, margin=0.5)
    vn, ins = tri.interpolate(q)
    vc, insc = tri.interpolate(q, outside="clamp")
    np.testing.assert_array_equal(ins, insc)
    assert (~ins).sum() > 100
    np.testing.assert_array_equal(vc[ins], vn[ins])
    assert np.isnan(vn[~ins]).all() and np.isfinite(vc[~ins]).all()
    # clamped values are convex combinations of sample values
    assert (vc[~ins] >= V.min(axis=0) - 1e-12).all()
    assert (vc[~ins] <= V.max(axis=0) + 1e-12).all()
    loc = tri.locate(q)
    out = ~loc.inside
    w = loc.weights[out]
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    assert (w[loc.ids[out] == -1] == 0).all()
    # a query far beyond a hull facet of a simplex gets that facet's values
    t2 = Triangulation(2)
    t2.insert([[0, 0], [1, 0], [0, 1]], [[0.0], [1.0], [3.0]])
    v, inside = t2.interpolate([[0.5, -2.0], [0.25, -1.0]], outside="clamp")
    assert not inside.any()
    np.testing.assert_allclose(v[:, 0], [0.5, 0.25], atol=1e-15)


def test_degenerate_and_empty():
    tri = Triangulation(3)
    assert tri.npoints == 0 and tri.nsimplex == 0 and tri.simplices.shape == (0, 4)
    v, ins = tri.interpolate(np.zeros((3, 3)), values=np.zeros((0, 1)))
    assert not ins.any() and np.isnan(v).all()
    tri.insert([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1.0], [2.0], [3.0]])  # a plane
    assert tri.current_dimension == 2
    loc = tri.locate([[0.1, 0.1, 0.0], [0.1, 0.1, 1.0]])
    assert (loc.kind == LocateKind.OUTSIDE_AFFINE_HULL).all()
    assert (loc.ids == -1).all() and np.isnan(loc.weights).all()
    v, ins = tri.interpolate([[0.1, 0.1, 0.0]], outside="clamp")
    assert not ins.any() and np.isnan(v).all()
    for t2 in (Triangulation.from_bytes(tri.to_bytes()), Triangulation.from_bytes(Triangulation(3).to_bytes())):
        assert t2.current_dimension in (2, -1)
    t2 = Triangulation.from_bytes(tri.to_bytes())
    np.testing.assert_array_equal(t2.points, tri.points)
    np.testing.assert_array_equal(t2.values, tri.values)
    t2.insert([[0, 0, 1.0]], [[4.0]])
    assert t2.nsimplex == 1 and t2.is_valid()


def test_dynamic_dimension_matches_scipy():
    D = 7
    rng = np.random.default_rng(13)
    tri, P, V = _filled(rng, D, 40)
    q = 0.3 + 0.4 * rng.random((300, D))
    ours, inside = _assert_matches_scipy(tri, P, V, q, rtol=1e-7)
    assert tri.is_valid()
    t2 = Triangulation.from_bytes(tri.to_bytes())
    v2, i2 = t2.interpolate(q)
    np.testing.assert_array_equal(i2, inside)
    np.testing.assert_array_equal(v2, ours)


def test_float32_values_and_values_argument():
    rng = np.random.default_rng(14)
    P, V = _sample(rng, 2, 200)
    tri = Triangulation(2)
    tri.insert(P, V.astype(np.float32))
    assert tri.values.dtype == np.float64
    q = _queries(rng, 2, 100, margin=0)
    a, _ = tri.interpolate(q)
    b, _ = tri.interpolate(q, values=V.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(a, b)
    c, ins = tri.interpolate(q, values=np.ones(200))
    assert ins.any()
    np.testing.assert_allclose(c[ins, 0], 1.0, atol=1e-12)


# ---------------------------------------------------------------- snapshots
def _built(D=4, n=600, C=2, seed=15):
    rng = np.random.default_rng(seed)
    P, V = _sample(rng, D, n, C)
    tri = Triangulation(D)
    tri.insert(P[: n // 2], V[: n // 2])
    tri.insert(P[n // 2:], V[n // 2:])
    return tri, rng


def _assert_same_answers(a, b, q):
    la, lb = a.locate(q), b.locate(q)
    for f in ("ids", "weights", "kind", "simplex"):
        np.testing.assert_array_equal(getattr(la, f), getattr(lb, f))
    va, ia = a.interpolate(q, outside="clamp")
    vb, ib = b.interpolate(q, outside="clamp")
    np.testing.assert_array_equal(va, vb)
    np.testing.assert_array_equal(ia, ib)


@pytest.mark.parametrize("D", [2, 4, 6])
def test_snapshot_roundtrip_file(tmp_path, D):
    tri, rng = _built(D=D, n=300 if D == 6 else 600)
    path = tmp_path / "t.fstri"
    tri.save(path)
    back = Triangulation.load(path)
    assert back.ndim == D and back.npoints == tri.npoints
    np.testing.assert_array_equal(back.points, tri.points)
    np.testing.assert_array_equal(back.values, tri.values)
    np.testing.assert_array_equal(back.simplices, tri.simplices)
    _assert_same_answers(tri, back, _queries(rng, D, 3 * CHUNK))
    assert back.is_valid()
    assert back.to_bytes() == tri.to_bytes() == path.read_bytes()
    # the loaded triangulation keeps growing like the original (same cells;
    # CGAL's insertion may order a new cell's vertices differently)
    P2 = rng.random((100, D))
    back.insert(P2, np.zeros((100, 2)))
    tri.insert(P2, np.zeros((100, 2)))
    assert back.is_valid()
    _assert_same_cells_and_values(tri, back, _queries(rng, D, 1000))


def test_snapshot_without_values(tmp_path):
    rng = np.random.default_rng(16)
    tri = Triangulation(3)
    tri.insert(rng.random((200, 3)))
    back = Triangulation.from_bytes(tri.to_bytes())
    assert back.values is None and back.nchannels == 0
    np.testing.assert_array_equal(back.simplices, tri.simplices)


def test_snapshot_truncated_raises(tmp_path):
    tri, _ = _built(D=3, n=300)
    data = tri.to_bytes()
    for cut in [0, 7, 40, 79, 80, 81, len(data) // 3, len(data) // 2, len(data) - 8, len(data) - 1]:
        with pytest.raises(SnapshotError):
            Triangulation.from_bytes(data[:cut])
        p = tmp_path / f"cut{cut}"
        p.write_bytes(data[:cut])
        with pytest.raises(SnapshotError):
            Triangulation.load(p)
    with pytest.raises(SnapshotError):
        Triangulation.load(tmp_path / "missing")


def test_snapshot_corrupted_raises(tmp_path):
    tri, rng = _built(D=3, n=300)
    data = bytearray(tri.to_bytes())
    positions = [0, 9, 17, 25, 49, 57, 73]  # header fields
    positions += sorted(rng.integers(80, len(data), 40).tolist())  # payload
    positions += [80, 80 + 300 * 3 * 8 + 5, len(data) - 1]  # points, ids, values
    for pos in positions:
        bad = bytearray(data)
        bad[pos] ^= 0x5A
        with pytest.raises(SnapshotError):
            Triangulation.from_bytes(bytes(bad))
    p = tmp_path / "bad"
    bad = bytearray(data)
    bad[len(data) // 2] ^= 1
    p.write_bytes(bytes(bad))
    with pytest.raises(SnapshotError):
        Triangulation.load(p)
    with pytest.raises(SnapshotError):
        Triangulation.from_bytes(b"not a snapshot at all" * 10)
    # extra trailing bytes are tolerated? no: announced payload must match
    Triangulation.from_bytes(bytes(data))  # the pristine copy still loads


def test_save_is_atomic_and_overwrites(tmp_path):
    tri, _ = _built(D=2, n=100)
    p = tmp_path / "s"
    p.write_bytes(b"old")
    tri.save(p)
    assert Triangulation.load(p).npoints == 100
    assert [x.name for x in tmp_path.iterdir()] == ["s"]


# ---------------------------------------------------------------- input errors
def test_bad_input_names_the_argument():
    tri = Triangulation(3)
    cases = [
        (lambda: tri.insert(np.zeros((4, 2))), "points"),
        (lambda: tri.insert([[0, 0, np.nan]]), "points"),
        (lambda: tri.insert("abc"), "points"),
        (lambda: tri.insert(np.eye(3), np.zeros((2, 1))), "values"),
        (lambda: tri.insert(np.eye(3), [[0.0], [np.inf], [1.0]]), "values"),
    ]
    for call, arg in cases:
        with pytest.raises(InvalidInputError) as ei:
            call()
        assert ei.value.argument == arg, (arg, ei.value)
        assert arg in str(ei.value)
    rng = np.random.default_rng(17)
    tri.insert(rng.random((50, 3)), rng.random((50, 2)))
    more = [
        (lambda: tri.insert(rng.random((5, 3))), "values"),
        (lambda: tri.insert(rng.random((5, 3)), rng.random((5, 3))), "values"),
        (lambda: tri.interpolate(np.zeros((2, 4))), "xi"),
        (lambda: tri.interpolate([[0, 0, np.nan]]), "xi"),
        (lambda: tri.interpolate(np.zeros((2, 3)), outside="zero"), "outside"),
        (lambda: tri.interpolate(np.zeros((2, 3)), order="random"), "order"),
        (lambda: tri.interpolate(np.zeros((2, 3)), threads=0), "threads"),
        (lambda: tri.interpolate(np.zeros((2, 3)), values=np.zeros((3, 1))), "values"),
        (lambda: tri.locate(np.zeros(2)), "xi"),
        (lambda: tri.find_simplex(np.zeros((1, 2))), "xi"),
        (lambda: Triangulation(1), "ndim"),
        (lambda: Triangulation(10**9), "ndim"),
    ]
    for call, arg in more:
        with pytest.raises(InvalidInputError) as ei:
            call()
        assert ei.value.argument == arg, (arg, ei.value)
    assert isinstance(InvalidInputError("x"), ValueError)


# ---------------------------------------------------------------- concurrency
def test_queries_concurrent_with_inserts():
    D = 3
    rng = np.random.default_rng(18)
    P, V = _sample(rng, D, 2000, C=1)
    tri = Triangulation(D)
    tri.insert(P[:500], V[:500])
    q = _queries(rng, D, 3 * CHUNK)
    errors = []
    stop = threading.Event()

    def reader():
        try:
            while not stop.is_set():
                v, ins = tri.interpolate(q, threads=1)
                assert np.isfinite(v[ins]).all()
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    readers = [threading.Thread(target=reader) for _ in range(3)]
    for t in readers:
        t.start()
    for lo in range(500, 2000, 100):
        tri.insert(P[lo:lo + 100], V[lo:lo + 100])
    stop.set()
    for t in readers:
        t.join()
    assert not errors
    assert tri.npoints == 2000 and tri.is_valid()
    ref = scipy_interp.LinearNDInterpolator(P, V)(q)
    ours, inside = tri.interpolate(q)
    np.testing.assert_allclose(ours[inside], ref[inside], atol=VALUE_TOL)


def _exact_det(rows) -> int:
    """Determinant of a square matrix of Python ints (Bareiss, fraction-free)."""
    m = [list(r) for r in rows]
    n, sign, prev = len(m), 1, 1
    for k in range(n - 1):
        if m[k][k] == 0:
            swap = next((i for i in range(k + 1, n) if m[i][k] != 0), None)
            if swap is None:
                return 0
            m[k], m[swap] = m[swap], m[k]
            sign = -sign
        for i in range(k + 1, n):
            for j in range(k + 1, n):
                m[i][j] = (m[i][j] * m[k][k] - m[i][k] * m[k][j]) // prev
        prev = m[k][k]
    return sign * m[n - 1][n - 1]


def _in_sphere(cell, q) -> int:
    """Sign of the lifted determinant rows (v - q, |v - q|^2), exactly."""
    return _exact_det([[*(vi - qi for vi, qi in zip(v, q)), sum((vi - qi) ** 2 for vi, qi in zip(v, q))]
                       for v in cell])


def _assert_delaunay_exactly(P, S, D, volume):
    """Exact checks of a triangulation of integer points P (tuples) by simplices S:
    non-degenerate cells whose volumes add up to ``volume`` (times D!), and no
    neighbour's opposite vertex strictly inside a cell's circumsphere."""
    vol = 0
    orient = []
    for s in S:
        v0 = P[s[0]]
        o = _exact_det([[P[i][j] - v0[j] for j in range(D)] for i in s[1:]])
        assert o != 0
        orient.append(1 if o > 0 else -1)
        vol += abs(o)
    assert vol == volume * int(np.prod(np.arange(1, D + 1)))
    # sign of (in_sphere * orientation) for a point strictly inside: the centroid
    c0 = [[(D + 1) * x for x in P[i]] for i in S[0]]
    cen = [sum(c[j] for c in c0) // (D + 1) for j in range(D)]
    inside = np.sign(_in_sphere(c0, cen)) * orient[0]
    facets = {}
    for ci, s in enumerate(S):
        for k in range(D + 1):
            facets.setdefault(tuple(sorted(np.delete(s, k))), []).append((ci, s[k]))
    checked = 0
    for pair in facets.values():
        assert len(pair) <= 2
        if len(pair) == 2:
            for (ci, _), (_, opp) in (pair, pair[::-1]):
                side = np.sign(_in_sphere([P[i] for i in S[ci]], P[opp])) * orient[ci]
                assert side != inside, (S[ci], opp)
                checked += 1
    return checked


def test_exact_delaunay_check_rejects_a_flipped_diagonal():
    P = [(0, 0), (4, 0), (5, 3), (0, 2)]  # convex; Delaunay diagonal: 1-3
    assert _assert_delaunay_exactly(P, np.array([[0, 1, 3], [1, 2, 3]]), 2, 11) == 2
    with pytest.raises(AssertionError):
        _assert_delaunay_exactly(P, np.array([[0, 1, 2], [0, 2, 3]]), 2, 11)


@pytest.mark.parametrize("D", [2, 3, 4, 5])
def test_delaunay_exactly_on_degenerate_integer_points(D):
    """The filtered predicates (native/fast_predicates.hpp) decide in floating point
    and defer to CGAL's exact ones near zero. On a lattice (cospherical and
    coplanar everywhere) plus random lattice points, checked with exact integers:
    cells are non-degenerate and tile the cube (volumes add up to it), and no
    neighbour's opposite vertex lies strictly inside a cell's circumsphere."""
    rng = np.random.default_rng(7 + D)
    side = {2: 8, 3: 4, 4: 3, 5: 2}[D]
    grid = np.stack(np.meshgrid(*[np.arange(0, 2 * side + 1, 2)] * D, indexing="ij"), -1).reshape(-1, D)
    extra = rng.integers(0, 2 * side + 1, (40, D))
    pts = np.unique(np.r_[grid, extra], axis=0)
    tri = Triangulation(D)
    tri.insert(pts.astype(np.float64))
    P = [tuple(int(x) for x in p) for p in tri.points]
    checked = _assert_delaunay_exactly(P, tri.simplices, D, (2 * side) ** D)
    assert checked > tri.nsimplex
    assert tri.is_valid()


def test_rwlock_lets_waiting_readers_in_between_writers():
    """A writer that takes the lock again at once (an insert in slices) lets the
    readers that waited for it in first; a waiting writer keeps new readers out."""
    from flatserve.triangulation import RWLock

    lock = RWLock()
    order, entered = [], threading.Event()
    lock.acquire_write()

    def reader():
        with lock.read():
            order.append("reader")
            entered.set()

    t = threading.Thread(target=reader)
    t.start()
    for _ in range(200):  # the reader is waiting for the writer
        if lock._waiting_readers:
            break
        threading.Event().wait(0.005)
    lock.release_write()
    lock.acquire_write()  # the next slice: only after the waiting reader went in
    order.append("writer")
    assert entered.is_set() and order == ["reader", "writer"]
    lock.release_write()
    t.join()

    lock.acquire_read()
    wants = threading.Thread(target=lambda: (lock.acquire_write(), order.append("w2"),
                                             lock.release_write()))
    wants.start()
    for _ in range(200):
        if lock._waiting_writers:
            break
        threading.Event().wait(0.005)
    late = threading.Thread(target=lambda: (lock.acquire_read(), order.append("late"),
                                            lock.release_read()))
    late.start()
    threading.Event().wait(0.05)
    assert "late" not in order  # the waiting writer keeps new readers out
    lock.release_read()
    wants.join(5)
    late.join(5)
    assert order[-2:] == ["w2", "late"]


def test_insert_in_slices_gives_the_same_triangulation():
    from flatserve import Basis, Field, Flats

    rng = np.random.default_rng(31)
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (3000, 3))
    screen = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)]
    flats = Flats.from_rays(eyes, screen - eyes)
    vals = rng.normal(size=(3000, 1))
    a, b = (Field(Basis.around_axis(), channels=1) for _ in range(2))
    ra = a.insert_prepared(a.prepare(flats, vals))
    rb = b.insert_prepared(b.prepare(flats, vals), slice_rows=700)
    assert (ra.accepted, ra.duplicates, ra.nsamples) == (rb.accepted, rb.duplicates, rb.nsamples)
    np.testing.assert_array_equal(a.points, b.points)
    q = Flats.from_rays(eyes[:500] + 0.01, screen[:500] - eyes[:500])
    np.testing.assert_allclose(a.query(q).values, b.query(q).values, atol=1e-12, equal_nan=True)
    with pytest.raises(ValueError, match="slice_rows"):
        b.insert_prepared(b.prepare(flats, vals), slice_rows=0)


# ---------------------------------------------------------------- within, seam_net
@pytest.mark.parametrize("D", [2, 4, 6])
def test_within_is_a_brute_force_distance_test(D):
    """``within`` against every pairwise distance (numpy), inside and outside the hull,
    at a radius that splits the queries; the same answer on any number of threads;
    empty and lower-dimensional triangulations answer too."""
    rng = np.random.default_rng(60 + D)
    P = rng.normal(size=(400, D))
    t = Triangulation(D)
    t.insert(P)
    Q = np.concatenate([rng.normal(size=(300, D)) * 1.5, P[:20]])
    dist = np.sqrt(((Q[:, None] - P[None]) ** 2).sum(axis=-1)).min(axis=1)
    radius = float(np.median(dist))
    got = t.within(Q, radius)
    np.testing.assert_array_equal(got, dist <= radius)
    assert 0.3 < got.mean() < 0.7
    np.testing.assert_array_equal(t.within(Q, radius, threads=1), got)
    assert t.within(Q, 0.0)[-20:].all()  # the samples themselves
    assert t.within(Q.reshape(2, -1, D), radius).shape == (2, len(Q) // 2)
    empty = Triangulation(D)
    assert not empty.within(Q, 10.0).any()
    flat = Triangulation(D)
    flat.insert(np.eye(D)[:2])  # lower-dimensional: no cell yet
    q = np.stack([np.eye(D)[0] * 1.1, np.eye(D)[1] * 1.1, -np.eye(D)[0]])
    np.testing.assert_array_equal(flat.within(q, 0.15), [True, True, False])


def test_within_and_seam_net_name_bad_input():
    t = Triangulation(3)
    t.insert(np.eye(3))
    for radius in (-1.0, float("nan"), float("inf"), 10**400, True, "1", None):
        with pytest.raises(InvalidInputError, match="radius") as err:
            t.within(np.zeros((1, 3)), radius)
        assert err.value.argument == "radius"
    with pytest.raises(InvalidInputError, match="xi"):
        t.within(np.zeros((1, 2)), 1.0)
    with pytest.raises(InvalidInputError, match="xi"):
        t.within([[np.nan, 0, 0]], 1.0)
    x = np.zeros((2, 3))
    for args, name in (((x, [0], x, [1, 2], 1.0), "cand_at"),
                       ((x, [1, 0], x, [2, 3], 1.0), "cand_at"),
                       ((x, [0, 1], np.zeros((2, 2)), [2, 3], 1.0), "base"),
                       ((x, [0, 1], x, [2, 3], -1.0), "radius"),
                       ((x, [0.2, 0.7], x, [2, 3], 1.0), "cand_at"),
                       ((x, [0, 1], x, [np.nan, 3], 1.0), "base_at"),
                       ((x, [0, 1], x, [3, 2], 1.0), "base_at"),
                       ((x, [0, 1], x, [2], 1.0), "base_at"),
                       ((x, [0, 1], x, ["a", "b"], 1.0), "base_at")):
        with pytest.raises(InvalidInputError) as err:
            seam_net(*args)
        assert err.value.argument == name, args
    for hit in ([False], [0.5, 0.5], [-1, 0]):
        with pytest.raises(InvalidInputError, match="hit"):
            seam_net(x, [0, 1], x, [2, 3], 1.0, hit=hit)


def test_seam_net_is_the_sequential_net_and_does_not_depend_on_cuts():
    """``seam_net`` against a plain loop over a stream of base points (always kept)
    and candidates (kept if no point kept before lies within the radius); the
    stream cut in pieces, each piece's kept points inserted into a triangulation
    whose ``within`` is the next piece's ``hit``, keeps the same candidates."""
    rng = np.random.default_rng(65)
    n, D, radius = 600, 3, 0.5
    X = rng.normal(size=(n, D))
    cand = rng.random(n) < 0.6
    kept, want = [], []
    for i in range(n):
        ok = not cand[i] or not kept or \
            np.sqrt(((np.array(kept) - X[i]) ** 2).sum(axis=1)).min() > radius
        if cand[i]:
            want.append(ok)
        if ok:
            kept.append(X[i])
    pos = np.arange(n)
    got = seam_net(X[cand], pos[cand], X[~cand], pos[~cand], radius)
    np.testing.assert_array_equal(got, want)
    assert 0.1 < np.mean(want) < 0.9
    t = Triangulation(D)
    pieces = []
    for lo, hi in ((0, 7), (7, 8), (8, 250), (250, 600)):
        c, b = pos[lo:hi][cand[lo:hi]], pos[lo:hi][~cand[lo:hi]]
        keep = seam_net(X[c], c, X[b], b, radius, hit=t.within(X[c], radius), threads=1)
        pieces.append(keep)
        t.insert(np.concatenate([X[b], X[c][keep]]))
    np.testing.assert_array_equal(np.concatenate(pieces), want)
