"""Flats (affine subspaces) as quadratic distance fields ``(Q, r)``, batched.

A k-flat in R^d (``0 <= k < d``) is stored as the pair of paper Eq. 2-3::

    Q = N N^T = I - A A^T      (d, d)   symmetric, idempotent, rank d-k   (C1)
    r = N c   = Q b            (d,)     fixed point of Q: Q r = r         (C2)

where ``A`` (d, k) holds orthonormal spanning vectors, ``N`` (d, d-k)
orthonormal normals, ``b`` any point of the flat and ``c = N^T b``.  ``r`` is
the point of the flat closest to the origin.  The squared distance of ``x`` to
the flat is ``x^T Q x - 2 r^T x + r^T r`` (Eq. 2).

Everything here is batched: ``n`` flats are arrays ``Q`` of shape (n, d, d) and
``r`` of shape (n, d); a flat is a row.  No function loops over flats in
Python.

Example
-------
>>> import numpy as np
>>> from flatserve import flats
>>> Q, r = flats.from_rays([[0.0, 0.0, -3.0]], [[0.0, 0.0, 1.0]])
>>> flats.squared_distance(Q, r, [[1.0, 0.0, 5.0]])
array([1.])
>>> p = flats.affine_combination([[0.5, 0.5]], *flats.from_rays(
...     [[0, 0, 0], [2, 0, 0]], [[0, 0, 1], [0, 0, 1]]), k=1)
>>> np.round(p.r, 12)
array([[1., 0., 0.]])
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._validate import as_array
from .errors import InvalidFlatError, InvalidInputError, WeightsError
from .options import Form

__all__ = [
    "FLAT_TOL",
    "GAP_TOL",
    "RANK_TOL",
    "PINV_RCOND",
    "WEIGHT_TOL",
    "Projection",
    "check_batch",
    "check_k",
    "from_parametric",
    "from_points",
    "from_normal",
    "from_rays",
    "to_parametric",
    "to_normal",
    "frames",
    "closest_point",
    "squared_distance",
    "validate",
    "project",
    "affine_combination",
    "basis_size",
    "FORMS",
    "FORM_WORDS",
    "forms_in_words",
    "form_shapes",
    "infer_form",
    "Flats",
]

#: Absolute tolerance of :func:`validate` for (C1) (``|Q - Q^T|``, ``|Q Q - Q|``,
#: ``|trace Q - (d-k)|``, max-norm) and (C2) (``|Q r - r| <= FLAT_TOL (1 + |r|)``).
FLAT_TOL = 1e-8
#: An eigen-gap ``lambda_{k+1} - lambda_k`` of ``Q*`` below this makes the
#: projection P (Sec. 2.3) ambiguous: the spanning eigenspace is not determined
#: (Sec. 3.1, Lemma 2).  Eigenvectors are perturbed by about ``eps / gap``, so
#: 1e-8 keeps them accurate to ~1e-8 relative.
GAP_TOL = 1e-8
#: A spanning matrix ``A`` (or normal matrix ``N``) whose smallest singular
#: value is below ``RANK_TOL`` times its largest is rank-deficient.
RANK_TOL = 1e-10
#: Eigenvalues of ``Q*`` with ``|lambda| <= PINV_RCOND * max|lambda|`` are
#: treated as zero by the pseudo-inverse of Sec. 2.3.
PINV_RCOND = 1e-12
#: Rows of affine weights must satisfy
#: ``|sum w - 1| <= WEIGHT_TOL * min(max(1, sum|w|), WEIGHT_SCALE_CAP)``: relative to
#: the weights' magnitude (rounding of large opposite weights), but never looser
#: than ``WEIGHT_TOL * WEIGHT_SCALE_CAP`` (weights so large that their sum cannot be
#: checked are refused, as are sums that overflow).
WEIGHT_TOL = 1e-9
WEIGHT_SCALE_CAP = 1e6


class Projection(NamedTuple):
    """Result of :func:`project` / :func:`affine_combination`.

    Attributes
    ----------
    Q : ndarray, shape (n, d, d)
        Projected ``Q~ = N N^T`` (valid flats, (C1)).
    r : ndarray, shape (n, d)
        Projected ``r~ = Q~ (Q*)^+ r*`` ((C2) holds).
    gap : ndarray, shape (n,)
        Eigen-gap ``lambda_{k+1} - lambda_k`` of ``Q*`` (ascending eigenvalues,
        1-based as in the paper; for ``k = 0`` it is ``lambda_1``).
    ambiguous : ndarray of bool, shape (n,)
        ``gap < gap_tol``: the projection is not unique and ``Q``, ``r`` of
        this row must not be trusted.
    """

    Q: np.ndarray
    r: np.ndarray
    gap: np.ndarray
    ambiguous: np.ndarray


# --------------------------------------------------------------------------- checks


def check_k(k, d: int, name: str = "k") -> int:
    """Return ``k`` as int after checking ``0 <= k < d``.

    Raises
    ------
    InvalidInputError
        Naming ``name`` when ``k`` is not an integer in ``[0, d)``.
    """
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
        raise InvalidInputError(f"{name}: expected an integer, got {k!r}", name)
    k = int(k)
    if not 0 <= k < d:
        raise InvalidInputError(f"{name}: need 0 <= k < d = {d}, got k = {k}", name)
    return k


#: largest magnitude of an entry of a flat's arrays (origins, directions, A, b, Q, r):
#: their products stay far from float64's limit (1.8e308), so no eigendecomposition
#: or SVD of a batch fails on one row's overflow
MAX_ENTRY = 1e100


def _as_flats(Q, r, name_Q: str = "Q", name_r: str = "r"):
    Q = as_array(Q, name_Q, ("n", None, None), max_abs=MAX_ENTRY)
    d = Q.shape[1]
    if d < 1 or Q.shape[2] != d:
        raise InvalidInputError(f"{name_Q}: expected shape (n, d, d), got {Q.shape}", name_Q)
    r = as_array(r, name_r, (Q.shape[0], d), max_abs=MAX_ENTRY)
    return Q, r


def _orthonormal_columns(M: np.ndarray, name: str, what: str):
    """SVD of a batch (n, d, j): returns (U (n,d,j), s (n,j), Vt (n,j,j))."""
    U, s, Vt = np.linalg.svd(M, full_matrices=False)
    smax = s[:, 0] if s.shape[1] else np.ones(M.shape[0])
    bad = (smax <= 0) | (s[:, -1] <= RANK_TOL * smax) if s.shape[1] else np.zeros(M.shape[0], bool)
    if bad.any():
        rows = np.nonzero(bad)[0]
        raise InvalidInputError(
            f"{name}: {what} are zero or linearly dependent (rank-deficient) in rows "
            f"{rows[:10].tolist()}" + (" ..." if rows.size > 10 else ""),
            name,
        )
    return U, s, Vt


# --------------------------------------------------------------------- constructors


def from_parametric(A, b):
    """Flats ``{A y + b}`` from parametric form (paper Sec. 2.1, Eq. 3).

    Parameters
    ----------
    A : array_like, shape (n, d, k)
        Spanning vectors as columns; need not be orthonormal but must have
        full column rank ``k`` (``k = 0`` gives points).
    b : array_like, shape (n, d)
        A point on each flat.

    Returns
    -------
    Q : ndarray, shape (n, d, d)
        ``I - U U^T`` with ``U`` an orthonormal basis of ``span(A)``.
    r : ndarray, shape (n, d)
        ``Q b``, the point of the flat closest to the origin.

    Raises
    ------
    InvalidInputError
        ``"A"`` for wrong shape, NaN, zero or linearly dependent columns,
        ``k >= d``; ``"b"`` for wrong shape or NaN.

    Examples
    --------
    >>> Q, r = from_parametric([[[1.0], [1.0]]], [[0.0, 2.0]])   # line y = x + 2
    >>> r
    array([[-1.,  1.]])
    """
    A = as_array(A, "A", ("n", None, None), max_abs=MAX_ENTRY)
    n, d, k = A.shape
    if d < 1:
        raise InvalidInputError(f"A: expected shape (n, d, k) with d >= 1, got {A.shape}", "A")
    check_k(k, d, "A")
    b = as_array(b, "b", (n, d), max_abs=MAX_ENTRY)
    I = np.eye(d)
    if k == 0:
        return np.broadcast_to(I, (n, d, d)).copy(), b.copy()
    U, _, _ = _orthonormal_columns(A, "A", "spanning vectors")
    Q = I - U @ np.swapaxes(U, 1, 2)
    r = np.einsum("nij,nj->ni", Q, b)
    return Q, r


def from_points(points):
    """Flats through ``k+1`` affinely independent points each.

    Parameters
    ----------
    points : array_like, shape (n, k+1, d)

    Returns
    -------
    Q : ndarray, shape (n, d, d)
    r : ndarray, shape (n, d)

    Raises
    ------
    InvalidInputError
        ``"points"`` for wrong shape, NaN, ``k >= d`` or affinely dependent
        points.

    Examples
    --------
    >>> Q, r = from_points([[[0.0, 1.0], [5.0, 1.0]]])   # the line y = 1
    >>> r
    array([[0., 1.]])
    """
    P = as_array(points, "points", ("n", None, None))
    n, kp1, d = P.shape
    if kp1 < 1 or d < 1:
        raise InvalidInputError(f"points: expected shape (n, k+1, d), got {P.shape}", "points")
    check_k(kp1 - 1, d, "points")
    A = np.swapaxes(P[:, 1:, :] - P[:, :1, :], 1, 2)  # (n, d, k)
    try:
        return from_parametric(A, P[:, 0, :])
    except InvalidInputError as exc:
        raise InvalidInputError(
            str(exc).replace("A:", "points:", 1).replace("spanning vectors", "point differences"),
            "points",
        ) from None


def from_normal(N, c):
    """Flats ``{x : N^T x = c}`` from normal form (paper Sec. 2.1, Eq. 2-3).

    Parameters
    ----------
    N : array_like, shape (n, d, d-k)
        Normal vectors as columns; full column rank, need not be orthonormal.
    c : array_like, shape (n, d-k)
        Right-hand sides (signed distances when ``N`` is orthonormal).

    Returns
    -------
    Q : ndarray, shape (n, d, d)
        ``U U^T`` with ``U`` an orthonormal basis of ``span(N)``.
    r : ndarray, shape (n, d)
        The closest point to the origin, ``U S^-1 V^T c`` for ``N = U S V^T``.

    Raises
    ------
    InvalidInputError
        ``"N"`` for wrong shape, NaN, ``d-k < 1`` or dependent normals;
        ``"c"`` for wrong shape or NaN.

    Examples
    --------
    >>> Q, r = from_normal([[[0.0], [2.0]]], [[2.0]])   # 2 y = 2
    >>> r
    array([[0., 1.]])
    """
    N = as_array(N, "N", ("n", None, None))
    n, d, j = N.shape
    if d < 1 or j < 1 or j > d:
        raise InvalidInputError(
            f"N: expected shape (n, d, d-k) with 1 <= d-k <= d, got {N.shape}", "N"
        )
    c = as_array(c, "c", (n, j))
    U, s, Vt = _orthonormal_columns(N, "N", "normal vectors")
    # N^T x = c  <=>  V S U^T x = c  <=>  U^T x = S^-1 V^T c
    y = np.einsum("nij,nj->ni", Vt, c) / s
    Q = U @ np.swapaxes(U, 1, 2)
    r = np.einsum("nij,nj->ni", U, y)
    return Q, r


def check_rays(origins, directions):
    """Validate rays; returns (origins (n,d), directions (n,d), |directions| (n,))."""
    o = as_array(origins, "origins", ("n", None), max_abs=MAX_ENTRY)
    d = o.shape[1]
    if d < 2:
        raise InvalidInputError(f"origins: lines need d >= 2, got d = {d}", "origins")
    v = as_array(directions, "directions", (o.shape[0], d), max_abs=MAX_ENTRY)
    norm = np.sqrt(np.einsum("ni,ni->n", v, v))
    bad = ~(norm > 0) | ~np.isfinite(norm)
    if bad.any():
        rows = np.nonzero(bad)[0]
        raise InvalidInputError(
            f"directions: zero (or overflowing) direction vectors in rows {rows[:10].tolist()}"
            + (" ..." if rows.size > 10 else ""),
            "directions",
        )
    return o, v, norm


def from_rays(origins, directions):
    """Lines (``k = 1``) through ``origins`` along ``directions``.

    Parameters
    ----------
    origins : array_like, shape (n, d)
    directions : array_like, shape (n, d)
        Non-zero; need not be normalised.

    Returns
    -------
    Q : ndarray, shape (n, d, d)
        ``I - a a^T`` with ``a = direction / |direction|``.
    r : ndarray, shape (n, d)
        ``Q origin``.

    Raises
    ------
    InvalidInputError
        ``"origins"``/``"directions"`` for wrong shape or NaN; ``"directions"``
        for zero (or overflowing) direction vectors; ``"origins"`` for ``d < 2``.

    Examples
    --------
    >>> Q, r = from_rays([[1.0, 2.0, 3.0]], [[0.0, 0.0, 2.0]])
    >>> r
    array([[1., 2., 0.]])
    """
    o, v, norm = check_rays(origins, directions)
    d = o.shape[1]
    a = v / norm[:, None]
    Q = np.eye(d) - a[:, :, None] * a[:, None, :]
    r = o - np.einsum("ni,ni->n", a, o)[:, None] * a
    return Q, r


# ------------------------------------------------------------------ back-conversions


def frames(Q, k):
    """Orthonormal spanning and normal vectors of flats (eigenvectors of ``Q``).

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    k : int

    Returns
    -------
    A : ndarray, shape (n, d, k)
        Eigenvectors of the ``k`` smallest eigenvalues (the null space, (C1)).
    N : ndarray, shape (n, d, d-k)
        Eigenvectors of the ``d-k`` largest eigenvalues (the image, (C1)).
    """
    Q = np.asarray(Q, dtype=np.float64)
    _, V = np.linalg.eigh(Q)
    return V[:, :, :k], V[:, :, k:]


def to_parametric(Q, r, k):
    """Orthonormal spanning vectors and the closest point to the origin.

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    r : array_like, shape (n, d)
    k : int

    Returns
    -------
    A : ndarray, shape (n, d, k)
        Orthonormal, ``span(A) = null(Q)``.
    b : ndarray, shape (n, d)
        ``r`` itself: for a valid flat the closest point to the origin (Eq. 3).

    Examples
    --------
    >>> Q, r = from_rays([[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    >>> A, b = to_parametric(Q, r, 1)
    >>> float(abs(A[0, 2, 0])), b[0]
    (1.0, array([1., 0., 0.]))
    """
    Q, r = _as_flats(Q, r)
    k = check_k(k, Q.shape[1])
    A, _ = frames(Q, k)
    return A, r.copy()


def to_normal(Q, r, k):
    """Orthonormal normals ``N`` and offsets ``c`` with ``flat = {N^T x = c}``.

    Parameters
    ----------
    Q, r : array_like, shapes (n, d, d) and (n, d)
        The flats' distance fields (Eq. 2): ``Q`` projects onto each flat's
        normal space, of dimension ``d - k``.
    k : int
        The flats' dimension.

    Returns
    -------
    N : ndarray, shape (n, d, d-k)
        Orthonormal, ``N N^T = Q`` (Eq. 3).
    c : ndarray, shape (n, d-k)
        ``N^T r`` (so ``r = N c``).

    Examples
    --------
    >>> Q, r = from_rays([[0.0, 0.0, 2.0]], [[0.0, 0.0, 1.0]])
    >>> N, c = to_normal(Q, r, 1)
    >>> N.shape, float(np.abs(c).max())
    ((1, 3, 2), 0.0)
    """
    Q, r = _as_flats(Q, r)
    k = check_k(k, Q.shape[1])
    _, N = frames(Q, k)
    return N, np.einsum("nij,ni->nj", N, r)


def closest_point(Q, r):
    """Point of each flat closest to the origin; this is ``r`` (Eq. 3).

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    r : array_like, shape (n, d)

    Returns
    -------
    ndarray, shape (n, d)
    """
    _, r = _as_flats(Q, r)
    return r.copy()


def squared_distance(Q, r, x):
    """Squared Euclidean distance of points to flats (paper Eq. 1-2).

    Computed as ``|Q x - r|^2``, which equals ``x^T Q x - 2 r^T x + r^T r``
    under (C1) and (C2) but never goes negative through cancellation.

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    r : array_like, shape (n, d)
    x : array_like, shape (n, d)
        One point per flat.

    Returns
    -------
    ndarray, shape (n,)
    """
    Q, r = _as_flats(Q, r)
    x = as_array(x, "x", r.shape)
    e = np.einsum("nij,nj->ni", Q, x) - r
    return np.einsum("ni,ni->n", e, e)


def validate(Q, r, k, tol: float = FLAT_TOL):
    """Check (C1) and (C2) of paper Sec. 2.1 for every row.

    (C1): ``Q`` symmetric, idempotent and of rank ``d - k`` (for a symmetric
    idempotent matrix the rank is its trace); (C2): ``Q r = r``.  All tests use
    the max-norm with absolute tolerance ``tol`` (``(C2)`` relative to
    ``1 + |r|``).

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    r : array_like, shape (n, d)
    k : int
    tol : float

    Returns
    -------
    Q, r : ndarray
        The validated arrays (float64, contiguous).

    Raises
    ------
    InvalidFlatError
        Naming the condition (``(C1) symmetric``, ``(C1) idempotent``,
        ``(C1) rank``, ``(C2) Qr = r``), the offending rows and the argument
        (``Q`` or ``r``).
    InvalidInputError
        For wrong shapes, NaN, or ``k`` outside ``[0, d)``.
    """
    Q, r = _as_flats(Q, r)
    d = Q.shape[1]
    k = check_k(k, d)

    def fail(mask, what, arg):
        rows = np.nonzero(mask)[0]
        raise InvalidFlatError(
            f"{arg}: condition {what} violated (tol {tol:g}) in rows {rows[:10].tolist()}"
            + (" ..." if rows.size > 10 else ""),
            arg,
        )

    Qt = np.swapaxes(Q, 1, 2)
    bad = np.abs(Q - Qt).max(axis=(1, 2)) > tol
    if bad.any():
        fail(bad, "(C1) symmetric", "Q")
    bad = np.abs(Q @ Q - Q).max(axis=(1, 2)) > tol
    if bad.any():
        fail(bad, "(C1) idempotent", "Q")
    bad = np.abs(np.trace(Q, axis1=1, axis2=2) - (d - k)) > tol * max(1, d)
    if bad.any():
        fail(bad, f"(C1) rank d-k = {d - k}", "Q")
    res = np.abs(np.einsum("nij,nj->ni", Q, r) - r).max(axis=1, initial=0.0)
    bad = res > tol * (1.0 + np.abs(r).max(axis=1, initial=0.0))
    if bad.any():
        fail(bad, "(C2) Qr = r", "r")
    return Q, r


# ------------------------------------------------------------------------ projection


def project_unchecked(Qs, rs, k, gap_tol: float = GAP_TOL) -> Projection:
    """:func:`project` without input checks, for arrays already validated
    (symmetric ``Qs`` (n, d, d), ``rs`` (n, d), ``0 <= k < d``)."""
    lam, V = np.linalg.eigh(Qs)
    if k == 0:
        gap = lam[:, 0].copy()
    else:
        gap = lam[:, k] - lam[:, k - 1]
    N = V[:, :, k:]
    lamN = lam[:, k:]
    scale = np.abs(lam).max(axis=1, keepdims=True)
    keep = np.abs(lamN) > PINV_RCOND * scale
    inv = np.where(keep, 1.0 / np.where(keep, lamN, 1.0), 0.0)
    # r~ = Q~ (Q*)^+ r* = N diag(1/lambda_N) N^T r*  (the k spanning terms vanish)
    y = np.einsum("nij,ni->nj", N, rs) * inv
    r = np.einsum("nij,nj->ni", N, y)
    Q = N @ np.swapaxes(N, 1, 2)
    return Projection(Q, r, gap, ~(gap >= gap_tol))


def project(Qs, rs, k, gap_tol: float = GAP_TOL) -> Projection:
    """Projection P of ``(Q*, r*)`` onto the closest k-flat (paper Sec. 2.3).

    1. ``Q* = V diag(lambda) V^T`` (ascending); the eigenvectors of the ``k``
       smallest eigenvalues span the flat, the rest ``N`` are its normals:
       ``Q~ = N N^T``.
    2. ``x* = (Q*)^+ r*`` (the extremum of ``q*``), ``r~ = Q~ x*``.

    Parameters
    ----------
    Qs : array_like, shape (n, d, d)
        Symmetric (e.g. an affine combination, Eq. 4, with weights summing
        to one so that eigenvalues are on the scale of ``[0, 1]``).
    rs : array_like, shape (n, d)
    k : int
    gap_tol : float
        Rows with eigen-gap ``lambda_{k+1} - lambda_k < gap_tol`` are flagged
        ``ambiguous`` (Sec. 3.1): their ``Q~`` is not unique.

    Returns
    -------
    Projection
        ``(Q (n,d,d), r (n,d), gap (n,), ambiguous (n,) bool)``.

    Examples
    --------
    >>> Q1, r1 = from_rays([[0, 0], [0, 2]], [[1, 0], [1, 0]])
    >>> p = project(0.5 * (Q1[:1] + Q1[1:]), 0.5 * (r1[:1] + r1[1:]), k=1)
    >>> p.r.round(12), bool(p.ambiguous[0])
    (array([[0., 1.]]), False)
    """
    Qs, rs = _as_flats(Qs, rs, "Qs", "rs")
    k = check_k(k, Qs.shape[1])
    return _project_checked(Qs, rs, k, gap_tol, "Qs")


def _project_checked(Qs, rs, k, gap_tol: float, arg: str) -> Projection:
    """:func:`project_unchecked` of finite input with a finite answer, else
    :class:`InvalidInputError` naming ``arg`` (never NaN out, nor LAPACK's "did not
    converge" in: entries near the float64 limit overflow inside the
    eigendecomposition)."""
    def too_large(rows) -> InvalidInputError:
        rows = np.flatnonzero(rows)
        return InvalidInputError(
            f"{arg}: rows {rows[:10].tolist()}{' ...' if rows.size > 10 else ''} overflow "
            "float64 when combined and projected (entries or weights too large); scale "
            "them down", arg)

    bad = ~(np.isfinite(Qs).all(axis=(1, 2)) & np.isfinite(rs).all(axis=1))
    if bad.any():
        raise too_large(bad)
    try:
        p = project_unchecked(Qs, rs, k, gap_tol)
    except np.linalg.LinAlgError:
        raise too_large(np.ones(len(Qs), bool)) from None
    bad = ~(np.isfinite(p.Q).all(axis=(1, 2)) & np.isfinite(p.r).all(axis=1))
    if bad.any():
        raise too_large(bad)
    return p


def _check_weights(weights, m):
    w = as_array(weights, "weights", ("n", m))
    s = w.sum(axis=1)
    scale = np.minimum(np.maximum(1.0, np.abs(w).sum(axis=1)), WEIGHT_SCALE_CAP)
    bad = ~(np.abs(s - 1.0) <= WEIGHT_TOL * scale)  # NaN/inf sums are bad too
    if bad.any():
        rows = np.nonzero(bad)[0]
        raise WeightsError(
            f"weights: rows must sum to one (Eq. 4); rows {rows[:10].tolist()}"
            + (" ..." if rows.size > 10 else "")
            + f" sum to {s[rows[:3]].tolist()}",
            "weights",
        )
    return w


def affine_combination(weights, Q, r, k, gap_tol: float = GAP_TOL) -> Projection:
    """Projected affine combinations ``P(sum_l w_l q_l)`` (paper Eq. 4, 6).

    Parameters
    ----------
    weights : array_like, shape (n, m)
        Each row sums to one (``WEIGHT_TOL``); negative entries are allowed
        (affine, not only convex, combinations).
    Q : array_like, shape (m, d, d)
        The flats being combined (need not be valid flats: tangent-simplex
        vertices are not).
    r : array_like, shape (m, d)
    k : int
    gap_tol : float
        See :func:`project`.

    Returns
    -------
    Projection

    Raises
    ------
    WeightsError
        ``"weights"`` when a row does not sum to one.

    Examples
    --------
    >>> Q, r = from_rays([[0.0, 0.0], [0.0, 4.0]], [[1.0, 0.0], [1.0, 0.0]])
    >>> affine_combination([[0.75, 0.25]], Q, r, k=1).r.round(12)
    array([[0., 1.]])
    """
    Q, r = _as_flats(Q, r)
    k = check_k(k, Q.shape[1])
    w = _check_weights(weights, Q.shape[0])
    Qs = np.einsum("nl,lij->nij", w, Q)
    rs = w @ r
    return _project_checked(Qs, rs, k, gap_tol, "weights")


# ------------------------------------------------------------------- sizes and batches


def basis_size(k: int, d: int) -> int:
    """Elements of a full basis of k-flats in R^d: ``m = (k+1)(d-k) + 1``.

    The manifold of k-flats in R^d has dimension ``(k+1)(d-k)`` (paper Sec. 3):
    a full basis (and the coordinate system of Fig. 8, one row per equation)
    has one more element; the triangulation of embedded coordinates has
    dimension ``m - 1``.

    Examples
    --------
    >>> basis_size(1, 3)          # lines in R^3: 5 basis lines, 4-D triangulation
    5
    """
    return (k + 1) * (d - k) + 1


#: The four forms a batch of flats can take, with the names of their arrays in
#: binary column order: rays (lines through an origin along a direction, k = 1),
#: parametric ``{A y + b}``, the quadrics ``(Q, r)`` of Eq. 3 and points (k = 0,
#: one array).
FORMS: dict[str, tuple[str, ...]] = {
    Form.RAYS.value: ("origins", "directions"),
    Form.PARAMETRIC.value: ("A", "b"),
    Form.FLATS.value: ("Q", "r"),
    Form.POINTS.value: ("points",),
}

#: What each form's arrays are, in words (the messages that ask for a form).
FORM_WORDS: dict[str, str] = {
    Form.RAYS.value: "origins+directions (rays)",
    Form.PARAMETRIC.value: "A+b (parametric)",
    Form.FLATS.value: "Q+r (flats)",
    Form.POINTS.value: "points (k = 0)",
}


def forms_in_words() -> str:
    """``origins+directions (rays), A+b (parametric), Q+r (flats) or points (k = 0)``."""
    words = list(FORM_WORDS.values())
    return ", ".join(words[:-1]) + " or " + words[-1]


def form_shapes(form: str, k: int, d: int) -> dict[str, tuple]:
    """Shapes of the arrays of ``form`` for k-flats in R^d (``"n"``: the rows).

    Raises
    ------
    InvalidInputError
        ``"form"`` for an unknown form, rays when ``k != 1`` or points when
        ``k != 0``.
    """
    if form == "rays":
        if k != 1:
            raise InvalidInputError(f"form: rays are lines (k = 1); these flats have k = {k}",
                                    "form")
        return {"origins": ("n", d), "directions": ("n", d)}
    if form == "points":
        if k != 0:
            raise InvalidInputError(
                f"form: points are 0-flats (k = 0); these are {k}-flats in R^{d} "
                f"(k = {k}, d = {d}): give A+b, Q+r" + (" or origins+directions" if k == 1
                                                         else ""), "form")
        return {"points": ("n", d)}
    if form == "parametric":
        return {"A": ("n", d, k), "b": ("n", d)}
    if form == "flats":
        return {"Q": ("n", d, d), "r": ("n", d)}
    raise InvalidInputError(f"form: one of {tuple(FORMS)}, got {form!r}", "form")


def infer_form(names) -> str | None:
    """The form whose array names occur in ``names`` (None when none does).

    Raises
    ------
    InvalidInputError
        When arrays of two forms are given (``"origins"`` and ``"Q"``, ...).
    """
    given = [f for f, arrs in FORMS.items() if any(a in names for a in arrs)]
    if len(given) > 1:
        raise InvalidInputError(
            "body: arrays of several forms given ("
            + " and ".join("+".join(FORMS[f]) for f in given) + "); give one", "body")
    return given[0] if given else None


class Flats:
    """An immutable batch of ``n`` k-flats in R^d, in one of four forms.

    The one type for "flats as input": :class:`flatserve.Field`, the service's
    codec and schemas and the client all take it. It is validated once when
    built; its arrays are read-only. ``(Q, r)`` is computed from the other forms
    on first use (rays keep their own fast coordinate path, so a ray batch
    never needs it).

    Parameters are given through the constructors :meth:`from_rays`,
    :meth:`from_parametric`, :meth:`from_quadrics`, :meth:`from_points` and
    :meth:`from_arrays`.

    Attributes
    ----------
    form : {"rays", "parametric", "flats", "points"}
    k, d : int
    arrays : dict of str to ndarray
        The form's arrays by name (:data:`FORMS`), float64, C-contiguous,
        read-only: ``origins``/``directions`` (n, d), ``A`` (n, d, k) / ``b``
        (n, d), ``Q`` (n, d, d) / ``r`` (n, d), or ``points`` (n, d) (k = 0).

    Examples
    --------
    >>> f = Flats.from_rays([[0.0, 0.0, -3.0]], [[0.0, 0.1, 1.0]])
    >>> f.form, f.k, f.d, len(f)
    ('rays', 1, 3, 1)
    >>> Q, r = f.quadrics()
    >>> Q.shape, r.shape
    ((1, 3, 3), (1, 3))
    """

    __slots__ = ("form", "k", "d", "arrays", "_quadrics")

    def __init__(self, form: str, k: int, d: int, arrays: dict, _quadrics=None):
        # Private: use the from_* constructors (they validate). A writable array may
        # be the caller's own, who could change it after validation: it is copied.
        self.form = form
        self.k = k
        self.d = d
        self.arrays = {name: _frozen(a) for name, a in arrays.items()}
        if form == "flats":
            _quadrics = (self.arrays["Q"], self.arrays["r"])
        elif _quadrics is not None:
            _quadrics = (_frozen(_quadrics[0]), _frozen(_quadrics[1]))
        self._quadrics = _quadrics

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_rays(cls, origins, directions) -> "Flats":
        """Lines through ``origins`` along ``directions`` (n, d) each; non-zero directions."""
        o, v, _ = check_rays(origins, directions)
        return cls("rays", 1, o.shape[1], {"origins": o, "directions": v})

    @classmethod
    def from_parametric(cls, A, b) -> "Flats":
        """Flats ``{A y + b}``: A (n, d, k) of full column rank, b (n, d)."""
        Q, r = from_parametric(A, b)  # validates (rank, shapes, NaN)
        A = as_array(A, "A", ("n", None, None))
        b = as_array(b, "b", (A.shape[0], A.shape[1]))
        return cls("parametric", A.shape[2], A.shape[1], {"A": A, "b": b}, (Q, r))

    @classmethod
    def from_quadrics(cls, Q, r, k, tol: float = FLAT_TOL) -> "Flats":
        """Flats as ``(Q (n, d, d), r (n, d))``; (C1) and (C2) are checked with ``tol``."""
        Q, r = validate(Q, r, k, tol)
        return cls("flats", int(k), Q.shape[1], {"Q": Q, "r": r}, (Q, r))

    @classmethod
    def from_points(cls, points) -> "Flats":
        """Points (k = 0 flats) of R^d: ``points`` (n, d), one point a row.

        The same flats as ``from_parametric`` with ``A`` of shape (n, d, 0) and
        ``b = points``, or ``from_quadrics`` with ``Q = I`` and ``r = points``.
        (Not :func:`from_points`, the module's function of flats through k+1
        points each: its ``points`` are (n, k+1, d).)

        Examples
        --------
        >>> f = Flats.from_points([[0.5, 0.25], [1.0, 0.0]])
        >>> f.form, f.k, f.d, len(f)
        ('points', 0, 2, 2)
        """
        P = as_array(points, "points", ("n", None), max_abs=MAX_ENTRY)
        if P.shape[1] < 1:
            raise InvalidInputError(f"points: expected shape (n, d) with d >= 1, got {P.shape}",
                                    "points")
        return cls("points", 0, P.shape[1], {"points": P})

    @classmethod
    def from_arrays(cls, arrays, *, k: int, d: int, form: str | None = None,
                    prefix: str = "", min_rows: int = 0) -> "Flats":
        """Flats from named arrays of any form (a JSON object, an ``.npz``, ...).

        Parameters
        ----------
        arrays : mapping of str to array_like
            ``origins`` + ``directions``, ``A`` + ``b``, ``Q`` + ``r`` or
            ``points`` (k = 0); other names are ignored (the caller decides
            whether they are allowed).
        k, d : int
            What the flats must be.
        form : str, optional
            The form; default inferred from the names (:func:`infer_form`).
        prefix : str
            Prepended (with a dot) to the argument named in errors
            (``"basis.center"`` makes ``"basis.center.Q"``).
        min_rows : int
            Fewest rows accepted.

        Raises
        ------
        InvalidInputError
            Naming the array (with ``prefix``): missing, wrong shape, NaN,
            unequal rows, invalid flats; or several forms given at once.
        """
        if form is None:
            form = infer_form(arrays)
            if form is None:
                raise InvalidInputError(f"{prefix or 'body'}: give {forms_in_words()}",
                                        prefix or "body")
        try:
            shapes = form_shapes(form, k, d)
        except InvalidInputError as exc:
            if not prefix:
                raise
            first = FORMS.get(form, ("form",))[0]
            raise InvalidInputError(f"{prefix}.{exc}", _join(prefix, first)) from None
        got = {}
        for name, shape in shapes.items():
            x = arrays.get(name)
            if x is None:
                said = getattr(form, "value", form)  # (a Form member: its value)
                raise InvalidInputError(_join(prefix, f"{name}: missing (form {said!r} needs "
                                        f"{list(shapes)})"), _join(prefix, name))
            if isinstance(x, list) and not x and min_rows:  # [] has no shape to check
                raise InvalidInputError(_join(prefix, f"{name}: expected at least one row, got 0"),
                                        _join(prefix, name))
            got[name] = as_array(x, _join(prefix, name), shape, max_abs=MAX_ENTRY)
        first, *rest = shapes
        if any(got[first].shape[0] != got[nm].shape[0] for nm in rest):
            rows = {nm: a.shape[0] for nm, a in got.items()}
            raise InvalidInputError(_join(prefix, f"rows differ between arrays: {rows}"),
                                    _join(prefix, rest[0]))
        if got[first].shape[0] < min_rows:
            want = "one row" if min_rows == 1 else f"{min_rows} rows"
            raise InvalidInputError(
                _join(prefix, f"{first}: expected at least {want}, got {got[first].shape[0]}"),
                _join(prefix, first))
        try:
            if form == "rays":
                return cls.from_rays(got["origins"], got["directions"])
            if form == "parametric":
                return cls.from_parametric(got["A"], got["b"])
            if form == "points":
                return cls.from_points(got["points"])
            return cls.from_quadrics(got["Q"], got["r"], k)
        except InvalidInputError as exc:
            if not prefix:
                raise
            raise type(exc)(f"{prefix}.{exc}", _join(prefix, exc.argument or "")) from None

    # ------------------------------------------------------------------ views
    @property
    def n(self) -> int:
        """Number of flats (rows)."""
        return int(next(iter(self.arrays.values())).shape[0])

    def __len__(self) -> int:
        return self.n

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Shapes of :attr:`arrays` by name."""
        return {name: a.shape for name, a in self.arrays.items()}

    def quadrics(self) -> tuple[np.ndarray, np.ndarray]:
        """``(Q (n, d, d), r (n, d))`` of the flats (Eq. 3), computed once."""
        if self._quadrics is None:
            if self.form == "points":
                P = self.arrays["points"]
                Q, r = np.broadcast_to(np.eye(self.d), (self.n, self.d, self.d)).copy(), P.copy()
            else:
                o, v = self.arrays["origins"], self.arrays["directions"]
                Q, r = from_rays(o, v)
            Q.setflags(write=False)
            r.setflags(write=False)
            self._quadrics = (Q, r)
        return self._quadrics

    def take(self, rows) -> "Flats":
        """The flats at ``rows`` (an index array or slice), same form."""
        q = self._quadrics
        return Flats(self.form, self.k, self.d,
                     {nm: _taken(a, rows) for nm, a in self.arrays.items()},
                     None if q is None else (_taken(q[0], rows), _taken(q[1], rows)))

    def __repr__(self) -> str:
        return f"Flats(form={self.form!r}, k={self.k}, d={self.d}, n={self.n})"


def _taken(a: np.ndarray, rows) -> np.ndarray:
    """``a[rows]`` contiguous and read-only, copied once: a fresh copy (an index
    array) is nobody else's, so it is frozen in place instead of copied again."""
    if isinstance(rows, np.ndarray) and rows.dtype.kind in "iu":
        t = np.take(a, rows, axis=0)  # = a[rows], a few times faster for 2-D and 3-D rows
    else:
        t = np.ascontiguousarray(a[rows])
    if t.flags.writeable and not np.may_share_memory(t, a):
        t.setflags(write=False)
    return t


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` read-only and contiguous, copied unless it already was read-only."""
    if a.flags.writeable or not a.flags.c_contiguous:
        a = np.array(a, dtype=np.float64, order="C")
    a.setflags(write=False)
    return a


def _join(prefix: str, text: str, sep: str = ".") -> str:
    return f"{prefix}{sep}{text}" if prefix else text


def check_batch(flats, k: int, d: int, holder: str) -> "Flats":
    """``flats`` if it is a :class:`Flats` batch of k-flats in R^d.

    Parameters
    ----------
    flats : object
    k, d : int
        What the holder takes.
    holder : str
        How the message names it: ``"this field holds"``, ``"this atlas charts"``.

    Raises
    ------
    InvalidInputError
        Not a batch (naming ``flats``), or of another (k, d) (naming the
        batch's first array).
    """
    if not isinstance(flats, Flats):
        raise InvalidInputError(
            f"flats: expected a flatserve.Flats batch, got {type(flats).__name__}", "flats")
    if flats.k != k or flats.d != d:
        arg = next(iter(flats.arrays))
        raise InvalidInputError(f"{arg}: {holder} {k}-flats in R^{d}, got "
                                f"{flats.k}-flats in R^{flats.d}", arg)
    return flats
