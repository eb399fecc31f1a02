"""Coordinates of flats in a basis of flats (paper Sec. 4, Fig. 8, Eq. 9, 12).

Given basis flats ``(Q_l, r_l)``, ``l = 1..m``, and a target flat
``(Q+, r+)`` with orthonormal spanning vectors ``a_i`` (``i = 1..k``) and
normals ``n_j`` (``j = 1..d-k``), the unknown weights ``w`` solve the linear
system ``M w = e`` of ``R = (k+1)(d-k) + 1`` rows (Fig. 8):

* ``k(d-k)`` orientation rows (Eq. 9), ordered ``i`` outer, ``j`` inner::

      sum_l w_l n_j^T Q_l a_i = 0

* ``d-k`` offset rows (Eq. 12)::

      sum_l w_l n_j^T (Q_l r+ - r_l) = 0

* one partition-of-unity row ``sum_l w_l = 1`` (right-hand side 1).

With ``m == R`` the system is square and solved exactly (LU).  When it is
numerically singular (``sigma_min <= rcond * sigma_max``) or not square, the
least-squares solution with ``sum w = 1`` kept exact is used (SVD
pseudo-inverse; the minimum-norm deviation from the barycentre, see
:func:`solve_system`).

A coordinate is only trustworthy if it *round-trips* (Sec. 4.3): recombining
the basis with ``w`` and projecting (Sec. 2.3) must give the target back.  The
round-trip residual is::

    residual = max(||Q~ - Q+||_F, ||r~ - r+||_2),    (Q~, r~) = P(sum_l w_l q_l)

(absolute: ``Q`` is dimensionless, ``r`` is in the units of the data, so keep
data on the scale of one).  Each target gets a status (:data:`Status`, the
extension's enum; one-line reasons in :data:`REASONS`), checked in this order:

``SINGULAR`` (2)
    the system is rank-deficient at this target: the coordinates are not
    determined (e.g. a basis containing orthogonal flats, Sec. 3.1).
``AMBIGUOUS`` (3)
    the recombined ``Q*`` has eigen-gap ``< gap_tol``: its projection is not
    unique (Lemma 2 does not apply).
``NOT_REPRESENTABLE`` (1)
    ``residual > roundtrip_tol``: the target is outside the chart the basis
    spans.  Least squares still returns *some* weights (Fig. 9 middle: a
    parallel-lines basis maps a non-parallel target onto a parallel line);
    they are reported, never silently used.
``OK`` (0)
    otherwise.

Fewer or more basis elements than ``(k+1)(d-k)+1`` (Fig. 9): with fewer the
system is overdetermined; targets in the (lower-dimensional) hull of the basis
are still recovered exactly and others fail the round trip.  With more the
system is underdetermined: the solution closest to the barycentre is returned, which may
differ from the weights that produced the target (the affine sum of two valid
coordinates need not be valid on the curved manifold) although it round-trips
when the target is reachable.

Example
-------
>>> import numpy as np
>>> from flatserve import flats
>>> from flatserve.coordinates import coordinates, OK
>>> Qb, rb = flats.from_rays([[0, 0], [0, 1], [1, 0]], [[1, 0], [1, 0.2], [1, -0.3]])
>>> p = flats.affine_combination([[0.2, 0.3, 0.5]], Qb, rb, k=1)
>>> c = coordinates(Qb, rb, 1, p.Q, p.r)
>>> np.round(c.weights, 10), c.status == OK
(array([[0.2, 0.3, 0.5]]), array([ True]))
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import _native
from . import flats as _flats
from ._validate import as_array
from .embedding import row_product
from .errors import InvalidInputError

__all__ = [
    "OK",
    "NOT_REPRESENTABLE",
    "SINGULAR",
    "AMBIGUOUS",
    "NO_SAMPLES",
    "Status",
    "REASONS",
    "reason",
    "ROUNDTRIP_TOL",
    "SINGULAR_RCOND",
    "Coordinates",
    "n_equations",
    "system_matrix",
    "solve_system",
    "roundtrip_residual",
    "coordinates",
    "coordinates_rays",
    "coordinates_of",
]

#: Status of one coordinate row: an :class:`enum.IntEnum` defined by the
#: extension (the C++ kernel writes the same codes), so members compare with
#: the int8 ``status`` arrays.
Status = _native.CoordinateStatus
OK = Status.OK
NOT_REPRESENTABLE = Status.NOT_REPRESENTABLE
SINGULAR = Status.SINGULAR
AMBIGUOUS = Status.AMBIGUOUS
#: A query's answer, never a coordinate kernel's: the flat lies in the domain of
#: a chart (its coordinates round-trip; for an atlas field, it is routed to
#: the chart), but that chart, and every other chart that holds it, has too
#: few samples to span a simplex (none, or all in one hyperplane of the
#: embedding: its triangulation's ``current_dimension`` is below ``ndim``).
#: An empty one-chart field answers it for every flat of its domain; an atlas
#: field answers ``NOT_REPRESENTABLE`` only where no chart's domain holds the flat.
NO_SAMPLES = Status.NO_SAMPLES
#: The one human-readable reason per status (field rejections, service docs).
REASONS: dict[Status, str] = {
    OK: "ok: the coordinates round-trip",
    NOT_REPRESENTABLE: "not representable: the coordinates do not round-trip "
    "(the flat lies outside the chart the basis spans)",
    SINGULAR: "singular: the coordinate system of the basis is singular at this flat",
    AMBIGUOUS: "ambiguous: the recombined flat has coinciding eigenvalues "
    "(eigen-gap below tolerance)",
    NO_SAMPLES: "no samples: the flat lies in a chart's domain, but the charts that hold it "
    "have too few samples to span a simplex (none yet)",
}


def reason(status) -> str:
    """The human-readable reason of one status code.

    Parameters
    ----------
    status : int or Status
        A code of a ``status`` array.

    Returns
    -------
    str
        ``REASONS[status]``, or ``"status <code>"`` for an unknown code.
    """
    return REASONS.get(status, f"status {status}")


#: Largest accepted round-trip residual ``max(||Q~-Q||_F, ||r~-r||)``.  Exact
#: coordinates round-trip to ~1e-12 for well-conditioned bases; 1e-6 leaves
#: room for the conditioning of small (scale 0.01) tangent simplices while
#: rejecting every target that is outside the chart (those miss by >> 1e-3).
ROUNDTRIP_TOL = 1e-6
#: The system of Fig. 8 is singular when ``sigma_min <= SINGULAR_RCOND * sigma_max``.
SINGULAR_RCOND = 1e-12


class Coordinates(NamedTuple):
    """Result of :func:`coordinates`.

    Attributes
    ----------
    weights : ndarray, shape (n, m)
        Affine coordinates (rows sum to one up to rounding).
    status : ndarray of int8, shape (n,)
        ``OK``, ``NOT_REPRESENTABLE``, ``SINGULAR`` or ``AMBIGUOUS`` (never
        ``NO_SAMPLES``: that is a field's answer, :meth:`flatserve.Field.query`).
    residual : ndarray, shape (n,)
        Round-trip residual ``max(||Q~-Q||_F, ||r~-r||)``.
    """

    weights: np.ndarray
    status: np.ndarray
    residual: np.ndarray


def n_equations(k: int, d: int) -> int:
    """Number of rows of the system of Fig. 8, ``(k+1)(d-k) + 1``."""
    return _flats.basis_size(k, d)


def system_matrix(Qb, rb, A, N, rt) -> np.ndarray:
    """The matrix of Fig. 8 (orientation rows, offset rows, a row of ones).

    Parameters
    ----------
    Qb : ndarray, shape (m, d, d) or (n, m, d, d)
        Basis ``Q_l`` (shared, or one basis per target).
    rb : ndarray, shape (m, d) or (n, m, d)
        Basis ``r_l``.
    A : ndarray, shape (n, d, k)
        Orthonormal spanning vectors ``a_i`` of the targets.
    N : ndarray, shape (n, d, d-k)
        Orthonormal normals ``n_j`` of the targets.
    rt : ndarray, shape (n, d)
        Target ``r``.

    Returns
    -------
    ndarray, shape (n, (k+1)(d-k)+1, m)
        Rows: ``n_j^T Q_l a_i`` (``i`` outer, Eq. 9), ``n_j^T (Q_l r - r_l)``
        (Eq. 12), ones.  The right-hand side is ``e_last``.
    """
    n, d, k = A.shape
    m = Qb.shape[-3]
    b = "n" if Qb.ndim == 4 else ""  # a basis per row (n, m, d, d) or shared (m, d, d)
    QA = np.einsum(f"{b}lde,nei->nlid", Qb, A)  # (n, m, k, d): Q_l a_i
    orient = np.einsum("ndj,nlid->nijl", N, QA).reshape(n, k * (d - k), m)
    off = np.einsum(f"{b}lde,ne->nld", Qb, rt) - (rb if b else rb[None])  # (n, m, d)
    offset = np.einsum("ndj,nld->njl", N, off)  # (n, d-k, m)
    return np.concatenate([orient, offset, np.ones((n, 1, m))], axis=1)


def solve_system(M, rcond: float = SINGULAR_RCOND):
    """Solve ``M w = e_last`` per row: LU when square and regular, else least squares.

    The last row of ``M`` (ones) is the partition of unity; it is kept exact
    in the least-squares case by writing ``w = 1/m + H z`` with ``H`` an
    orthonormal basis of ``{sum = 0}`` and solving ``min |M_o H z + M_o 1/m|``
    for the minimum-norm ``z`` (``M_o``: all rows but the last).  So weights
    always sum to one, and among several solutions (more basis elements than
    rows) the one closest to the barycentre is returned.

    Parameters
    ----------
    M : ndarray, shape (n, R, m)
    rcond : float
        Singularity threshold on ``sigma_min / sigma_max`` of ``M_o H``.

    Returns
    -------
    w : ndarray, shape (n, m)
    singular : ndarray of bool, shape (n,)
        ``M_o H`` has numerical rank below ``min(R-1, m-1)``.
    """
    from .embedding import regular_simplex

    n, R, m = M.shape
    w = np.empty((n, m))
    if n == 0:
        return w, np.zeros(0, bool)
    if m == 1:
        w[:] = 1.0
        return w, np.zeros(n, bool)
    H = regular_simplex(m)  # (m, m-1), orthonormal columns orthogonal to ones
    Mo = M[:, :-1, :]
    B = Mo @ H  # (n, R-1, m-1)
    c = -Mo.sum(axis=2) / m  # rhs for z
    U, s, Vt = np.linalg.svd(B, full_matrices=False)
    singular = ~(s[:, -1] > rcond * s[:, 0])
    exact = ~singular if R == m else np.zeros(n, bool)
    if exact.any():
        e = np.zeros((int(exact.sum()), R, 1))
        e[:, -1, 0] = 1.0
        w[exact] = np.linalg.solve(M[exact], e)[:, :, 0]
    rest = ~exact
    if rest.any():
        keep = s[rest] > rcond * s[rest, :1]
        inv = np.where(keep, 1.0 / np.where(keep, s[rest], 1.0), 0.0)
        y = np.einsum("nji,nj->ni", U[rest], c[rest]) * inv
        z = np.einsum("nji,nj->ni", Vt[rest], y)
        w[rest] = 1.0 / m + row_product(z, H.T)  # a row's bits: its own (see there)
    return w, singular


def roundtrip_residual(weights, Qb, rb, k, Qt, rt, gap_tol: float = _flats.GAP_TOL):
    """Recombine, project (Sec. 2.3) and compare with the targets.

    Parameters
    ----------
    weights : ndarray, shape (n, m)
    Qb, rb : ndarray, shapes (m, d, d), (m, d), or a basis per row (n, m, d, d), (n, m, d)
    k : int
    Qt, rt : ndarray, shapes (n, d, d), (n, d)
        The targets.
    gap_tol : float

    Returns
    -------
    residual : ndarray, shape (n,)
        ``max(||Q~ - Qt||_F, ||r~ - rt||_2)``.
    ambiguous : ndarray of bool, shape (n,)
        Eigen-gap of the recombination below ``gap_tol``.
    """
    if Qb.ndim == 4:  # a basis per row
        Qs = np.einsum("nl,nlij->nij", weights, Qb)
        rs = np.einsum("nl,nli->ni", weights, rb)
    else:
        Qs = np.einsum("nl,lij->nij", weights, Qb)
        rs = weights @ rb
    # a row that overflows (entries near the float64 limit) fails its round trip
    # alone: it is projected as zeros, and LAPACK never sees an inf
    over = ~(np.isfinite(Qs).all(axis=(1, 2)) & np.isfinite(rs).all(axis=1))
    if over.any():
        Qs, rs = np.where(over[:, None, None], 0.0, Qs), np.where(over[:, None], 0.0, rs)
    try:
        p = _flats.project_unchecked(Qs, rs, k, gap_tol)
    except np.linalg.LinAlgError:  # finite but overflowing inside: the rows one by one
        parts = []
        for i in range(len(Qs)):
            try:
                parts.append(_flats.project_unchecked(Qs[i:i + 1], rs[i:i + 1], k, gap_tol))
            except np.linalg.LinAlgError:
                over[i] = True
                parts.append(_flats.project_unchecked(np.zeros_like(Qs[i:i + 1]),
                                                      np.zeros_like(rs[i:i + 1]), k, gap_tol))
        p = _flats.Projection(*(np.concatenate(a) for a in zip(*parts)))
    eQ = np.sqrt(((p.Q - Qt) ** 2).sum(axis=(1, 2)))
    er = np.sqrt(((p.r - rt) ** 2).sum(axis=1))
    res = np.maximum(eQ, er)
    res[~np.isfinite(res) | over] = np.inf
    return res, p.ambiguous


def coordinates(
    Qb,
    rb,
    k,
    Q,
    r,
    roundtrip_tol: float = ROUNDTRIP_TOL,
    rcond: float = SINGULAR_RCOND,
    gap_tol: float = _flats.GAP_TOL,
    check: bool = True,
    flat_tol: float = _flats.FLAT_TOL,
    native: bool | None = None,
) -> Coordinates:
    """Affine coordinates of target flats in a basis (Fig. 8, Eq. 9, 12).

    Parameters
    ----------
    Qb : array_like, shape (m, d, d)
        Basis ``Q_l`` (tangent-simplex vertices need not be valid flats).
    rb : array_like, shape (m, d)
    k : int
    Q : array_like, shape (n, d, d)
        Target flats (validated with :func:`flatserve.flats.validate` when
        ``check``).
    r : array_like, shape (n, d)
    roundtrip_tol, rcond, gap_tol : float
        See the module docstring.
    check : bool
        Validate (C1)/(C2) of the targets (raises ``InvalidFlatError``).
    flat_tol : float
        Tolerance of that validation.
    native : bool or None
        Lines in R^3 with a 5-element basis go through the native fast path
        (see :func:`coordinates_rays`; the line's direction is the largest
        column of ``I - Q``, its origin ``r``) unless ``native`` is False.

    Returns
    -------
    Coordinates
        ``weights (n, m)``, ``status (n,) int8``, ``residual (n,)``.
    """
    Qb = as_array(Qb, "Qb", ("m", None, None))
    m, d, d2 = Qb.shape
    if d < 1 or d2 != d or m < 1:
        raise InvalidInputError(f"Qb: expected shape (m, d, d), got {Qb.shape}", "Qb")
    rb = as_array(rb, "rb", (m, d))
    k = _flats.check_k(k, d)
    if d - k < 1:
        raise InvalidInputError("k: need k < d", "k")
    Q = as_array(Q, "Q", ("n", d, d))
    r = as_array(r, "r", (Q.shape[0], d))
    if check:
        _flats.validate(Q, r, k, flat_tol)
    if native is not False and (k, d, m) == (1, 3, 5) and Q.shape[0]:
        P = np.eye(3) - Q  # = a a^T
        col = np.argmax(np.diagonal(P, axis1=1, axis2=2), axis=1)
        directions = np.ascontiguousarray(np.take_along_axis(P, col[:, None, None], 2)[:, :, 0])
        return coordinates_rays(Qb, rb, r, directions, roundtrip_tol, rcond, gap_tol, native)
    return coordinates_unchecked(Qb, rb, k, Q, r, roundtrip_tol, rcond, gap_tol)


def coordinates_unchecked(Qb, rb, k, Q, r, roundtrip_tol=ROUNDTRIP_TOL,
                           rcond=SINGULAR_RCOND, gap_tol=_flats.GAP_TOL) -> Coordinates:
    """:func:`coordinates` without input checks; ``Qb`` may be (n, m, d, d)."""
    A, N = _flats.frames(Q, k)
    M = system_matrix(Qb, rb, A, N, r)
    w, singular = solve_system(M, rcond)
    residual, ambiguous = roundtrip_residual(w, Qb, rb, k, Q, r, gap_tol)
    status = np.full(Q.shape[0], OK, dtype=np.int8)
    status[~(residual <= roundtrip_tol)] = NOT_REPRESENTABLE
    status[ambiguous] = AMBIGUOUS
    status[singular] = SINGULAR
    return Coordinates(w, status, residual)


def coordinates_rays(Qb, rb, origins, directions, roundtrip_tol: float = ROUNDTRIP_TOL,
                     rcond: float = SINGULAR_RCOND, gap_tol: float = _flats.GAP_TOL,
                     native: bool | None = None, threads: int | None = None) -> Coordinates:
    """Coordinates of lines given as ``origins + t directions`` (``k = 1``).

    Same result as ``coordinates(Qb, rb, 1, *from_rays(origins, directions))``.
    For ``d = 3`` and ``m = 5`` the fast path (native C++,
    ``native/coordinates.hpp``: one pass per ray, no temporaries, the GIL
    released, rows split over ``threads``) is used unless ``native`` is
    False.  It agrees with the NumPy reference to rounding and gives
    bit-identical results for any thread count (tested).  The extension
    always provides it: a build without it raises ``RuntimeError`` rather
    than silently taking the slow path.

    Parameters
    ----------
    Qb : array_like, shape (m, d, d)
    rb : array_like, shape (m, d)
    origins, directions : array_like, shape (n, d)
    roundtrip_tol, rcond, gap_tol : float
    native : bool or None
        ``None``: the fast path for ``d = 3, m = 5``, else the reference;
        ``False``: the NumPy reference; ``True``: require the fast path
        (``RuntimeError`` when ``(m, d) != (5, 3)``).
    threads : int, optional
        Worker threads of the fast path (default: all cores for big batches,
        one for small ones). Results do not depend on it.

    Returns
    -------
    Coordinates
    """
    Qb = as_array(Qb, "Qb", ("m", None, None))
    m, d, _ = Qb.shape
    rb = as_array(rb, "rb", (m, d))
    o, v, _ = _flats.check_rays(origins, directions)
    if o.shape[1] != d:
        raise InvalidInputError(f"origins: basis is in R^{d}, rays in R^{o.shape[1]}", "origins")
    th = _threads_arg(threads)
    fast = _fast_rays() if native is not False and (m, d) == (5, 3) else None
    if native and fast is None:
        raise RuntimeError("the native coordinates fast path needs d = 3 and m = 5, "
                           f"got d = {d}, m = {m}")
    if fast is not None:
        w, status, residual = fast(Qb, rb, o, v, roundtrip_tol, rcond, gap_tol, th)
        return Coordinates(w, status, residual)
    Q, r = _flats.from_rays(o, v)
    return coordinates_unchecked(Qb, rb, 1, Q, r, roundtrip_tol, rcond, gap_tol)


def _threads_arg(threads) -> int:
    """``threads`` for the native kernel: 0 (automatic) for None, else a positive int."""
    if threads is None:
        return 0
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InvalidInputError(f"threads: expected a positive integer or None, got {threads!r}",
                                "threads")
    return int(threads)


def _fast_rays():
    """The native kernel (``d = 3, m = 5``) wrapped to take validated float64 arrays.

    Raises
    ------
    RuntimeError
        ``_native.coordinates_rays3`` was replaced by ``None`` (tests do this
        to check that there is never a silent slow fallback).
    """
    kernel = _native.coordinates_rays3
    if kernel is None:
        raise RuntimeError("flatserve._core.coordinates_rays3 is missing; rebuild (make build)")

    def fast(Qb, rb, o, v, roundtrip_tol, rcond, gap_tol, threads=0):
        return kernel(np.ascontiguousarray(Qb), np.ascontiguousarray(rb), o, v,
                      float(roundtrip_tol), float(rcond), float(gap_tol),
                      float(_flats.PINV_RCOND), int(threads))

    return fast


def coordinates_of(Qb, rb, k: int, flats, roundtrip_tol: float = ROUNDTRIP_TOL,
                   rcond: float = SINGULAR_RCOND, gap_tol: float = _flats.GAP_TOL,
                   threads: int | None = None) -> Coordinates:
    """Coordinates of a validated :class:`flatserve.flats.Flats` batch in a basis.

    The checks done when ``flats`` was built are not repeated. Rays take the
    lines' fast path (:func:`coordinates_rays`: no ``(Q, r)`` is built; native
    for ``d = 3, m = 5``); the other forms go through their quadrics.

    Parameters
    ----------
    Qb : ndarray, shape (m, d, d)
    rb : ndarray, shape (m, d)
        The basis (validated by :class:`flatserve.Basis`).
    k : int
    flats : Flats
        Of dimension ``k`` in R^d.
    roundtrip_tol, rcond, gap_tol : float
    threads : int, optional
        Threads of the native fast path; results do not depend on it.

    Returns
    -------
    Coordinates
    """
    m, d = Qb.shape[0], Qb.shape[1]
    if flats.d != d or flats.k != k:
        arg = next(iter(flats.arrays))
        raise InvalidInputError(f"{arg}: expected {k}-flats in R^{d}, got {flats.k}-flats in "
                                f"R^{flats.d}", arg)
    if flats.form == "rays":
        th = _threads_arg(threads)
        if (m, d) == (5, 3):
            w, status, residual = _fast_rays()(Qb, rb, flats.arrays["origins"],
                                               flats.arrays["directions"], roundtrip_tol, rcond,
                                               gap_tol, th)
            return Coordinates(w, status, residual)
    Q, r = flats.quadrics()
    return coordinates_unchecked(Qb, rb, k, Q, r, roundtrip_tol, rcond, gap_tol)
