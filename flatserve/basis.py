"""Bases of flats (paper Sec. 3) and the tangent-space base simplex (Sec. 5.1).

A basis is ``m`` flats ``(Q_l, r_l)`` of dimension ``k`` in R^d; a full basis
has ``m = (k+1)(d-k) + 1`` elements (the manifold of k-flats has dimension
``(k+1)(d-k)``).  :meth:`Basis.coordinates` returns the affine coordinates of
targets (Fig. 8, see :mod:`flatserve.coordinates`), :meth:`Basis.check` the
checks of Sec. 3 that can be computed.

Tangent simplex (Sec. 5.1, Eq. 13-15), generalised to any ``(k, d)``
--------------------------------------------------------------------
Around a centre flat with orthonormal spanning vectors ``a_i`` (d, k), normals
``n_j`` (d, d-k) and offset ``r0 = sum_j alpha_j n_j``, the ``D = (k+1)(d-k)``
tangent directions of the ``(Q, r)`` manifold are

* rotation of ``a_i`` toward ``n_j`` (``i`` outer, ``j`` inner), ``k(d-k)`` of
  them: with ``R(t) = exp(t (n_j a_i^T - a_i n_j^T))`` applied to the frame,
  ``Q(t) = I - R A A^T R^T`` and ``r(t) = R N alpha`` give::

      dQ = -(n_j a_i^T + a_i n_j^T),     dr = -alpha_j a_i          ("tangent")

  Eq. 14 as printed instead reads ``dQ = -(n_j a_i^T + a_i n_j^T) + a_i a_i^T``,
  ``dr = +alpha_j a_i``                                            ("paper")

* offset along ``n_j``, ``d-k`` of them: ``dQ = 0``, ``dr = n_j``.

The vertices are ``(Q_l, r_l) = (Q0, r0) + scale * sum_c S[c, l] G_c`` with
``S`` a regular simplex of ``D + 1`` vertices centred at the origin of R^D
(for ``D = 4`` exactly ``S_4`` of Eq. 15; otherwise a regular simplex with the
same edge length ``2 sqrt(2)``).  The vertices are *not* projected onto the
manifold (as in the paper): they are points of the tangent plane.

Why ``variant="tangent"`` is the default
    The ``+ a_i a_i^T`` term of Eq. 14 is not a derivative of ``I - A A^T``
    (``d/dt`` of an idempotent ``Q`` has no component in ``null(Q)``; a finite
    difference test in ``tests/test_basis.py`` shows it).  It lifts the zero
    eigenvalue of the centre direction by ``scale * (S_1l + S_2l)`` per
    vertex, i.e. it pushes the vertices off the tangent plane along the
    manifold's normal, by as much as the rotation itself.  The chart of the
    true tangent simplex reaches every line within 45 degrees of the axis
    (``Q* ~ I - a a^T - t (n a^T + a n^T)`` has its smallest eigenvector at
    ``tan(2 phi) = 2 t``, i.e. ``phi < 45 deg`` for all ``t``); the skewed one
    reaches less.  Measured on the paper's ray set-up (screen z = 0 in
    ``[-1, 1]^2``, eyes in ``[-1, 1]^2 x [-4.5, -1.5]``, basis around the
    z-axis, scale 0.01, 1M rays): Eq. 14 as printed loses 6.95 % of the rays,
    the tangent variant 1.74 %, exactly the share of rays steeper than 45
    degrees (``benchmarks/bench_coordinates.py`` prints both).  Projecting the
    Eq. 14 vertices onto the manifold removes the ``a a^T`` component and
    gives the tangent variant's 1.74 % back.

Example
-------
>>> import numpy as np
>>> from flatserve.basis import Basis
>>> from flatserve import flats
>>> B = Basis.around_axis(axis=2, scale=0.01)          # 5 lines around the z-axis
>>> B.m, B.dim
(5, 4)
>>> Q, r = flats.from_rays([[0.1, 0.2, -3.0]], [[0.05, -0.1, 1.0]])
>>> c = B.coordinates(Q, r)
>>> int(c.status[0]), bool(c.residual[0] < 1e-9)
(0, True)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from . import coordinates as _coords
from . import flats as _flats
from ._validate import as_array
from .embedding import regular_simplex
from .errors import BasisError, InvalidInputError

__all__ = [
    "Basis",
    "BasisReport",
    "ScaleSelection",
    "DEFAULT_VARIANT",
    "VARIANTS",
    "ORTHOGONAL_TOL",
    "S4",
    "tangent_directions",
    "simplex_vertices",
    "select_scale",
    "CONVEX_TOL",
]

#: Tangent-simplex variants: ``"tangent"`` (true derivative) and ``"paper"``
#: (Eq. 14 exactly as printed).
VARIANTS = ("tangent", "paper")
#: The variant that round-trips more samples (module docstring).
DEFAULT_VARIANT = "tangent"
#: Two basis flats count as orthogonal (Sec. 3.1) when ``Q(1/2) = (Q_i+Q_j)/2``
#: has an eigenvalue within ``ORTHOGONAL_TOL / 2`` of ``1/2`` (Lemma 1: only
#: orthogonal flats give ``Q(mu)`` the eigenvalue ``mu``).  The measure
#: ``2 min |lambda - 1/2|`` is the cosine of the largest principal angle
#: between the two direction spaces for lines.
ORTHOGONAL_TOL = 1e-6

#: :meth:`Basis.check` probes the coordinate system at flats this far from the
#: barycentre (in the units of the data; charts are used at this scale and beyond).
PROBE_DISTANCE = 1.0

#: The regular 4-simplex of Eq. 15 (columns are vertices).
S4 = np.array(
    [
        [1.0, 1.0, -1.0, -1.0, 0.0],
        [1.0, -1.0, 1.0, -1.0, 0.0],
        [1.0, -1.0, -1.0, 1.0, 0.0],
        [-(5**-0.5), -(5**-0.5), -(5**-0.5), -(5**-0.5), 4 * 5**-0.5],
    ]
)
S4.setflags(write=False)


def simplex_vertices(D: int) -> np.ndarray:
    """Regular simplex of ``D+1`` vertices centred at the origin of R^D.

    Returns
    -------
    ndarray, shape (D, D+1)
        Columns are vertices, edge length ``2 sqrt(2)``; ``S4`` (Eq. 15) for
        ``D = 4``.
    """
    if D == 4:
        return np.array(S4)
    return 2.0 * regular_simplex(D + 1).T


def _orthonormal(M, name):
    M = np.asarray(M, dtype=np.float64)
    if M.shape[1] == 0:
        return M
    U, s, Vt = np.linalg.svd(M[None], full_matrices=False)
    if not (s[0, -1] > 1e-10 * s[0, 0]):
        raise InvalidInputError(f"{name}: columns are linearly dependent", name)
    return (U @ Vt)[0]  # closest orthonormal matrix (keeps the given order/orientation)


def tangent_directions(A, N, alpha, variant: str = DEFAULT_VARIANT):
    """The ``D = (k+1)(d-k)`` tangent directions of Sec. 5.1 (Eq. 14, generalised).

    Parameters
    ----------
    A : ndarray, shape (d, k)
        Orthonormal spanning vectors of the centre flat.
    N : ndarray, shape (d, d-k)
        Orthonormal normals.
    alpha : ndarray, shape (d-k,)
        Offset of the centre, ``r0 = N alpha``.
    variant : {"tangent", "paper"}

    Returns
    -------
    dQ : ndarray, shape (D, d, d)
        Rotation directions (``i`` outer, ``j`` inner), then ``d-k`` zeros.
    dr : ndarray, shape (D, d)
        ``-alpha_j a_i`` ("tangent") / ``+alpha_j a_i`` ("paper"), then ``n_j``.
    """
    if variant not in VARIANTS:
        raise InvalidInputError(f"variant: expected one of {VARIANTS}, got {variant!r}", "variant")
    d, k = A.shape
    c = d - k
    D = _flats.basis_size(k, d) - 1
    dQ = np.zeros((D, d, d))
    dr = np.zeros((D, d))
    sign = -1.0 if variant == "tangent" else 1.0
    idx = 0
    for i in range(k):  # D is small: loops over directions, not over flats
        a = A[:, i]
        for j in range(c):
            n = N[:, j]
            dQ[idx] = -(np.outer(n, a) + np.outer(a, n))
            if variant == "paper":
                dQ[idx] += np.outer(a, a)
            dr[idx] = sign * alpha[j] * a
            idx += 1
    for j in range(c):
        dr[idx] = N[:, j]
        idx += 1
    return dQ, dr


@dataclass
class BasisReport:
    """Outcome of :meth:`Basis.check` (the computable checks of Sec. 3).

    Attributes
    ----------
    m, expected_m : int
        Number of basis flats and ``(k+1)(d-k)+1``.
    count_ok : bool
        ``m == expected_m``.
    orthogonal_pairs : list of (int, int)
        Pairs whose measure (see ``ORTHOGONAL_TOL``) is below tolerance; two
        orthogonal flats do not span a one-dimensional space (Sec. 3.1).
    min_pair_measure : float
        Smallest ``2 min |lambda(Q(1/2)) - 1/2|`` over all pairs.
    barycentre_gap : float
        Eigen-gap of the barycentre ``sum Q_l / m`` (must not be ambiguous).
    barycentre_condition : float
        ``sigma_min / sigma_max`` of the system of Fig. 8 (reduced to
        ``sum w = 1``, see :func:`flatserve.coordinates.solve_system`) at the
        projected barycentre (0 = singular coordinate system).
    barycentre_error : float
        ``max |w - 1/m|`` of the coordinates recovered for the barycentre.
    failures : list of str
        One message per failed check; empty when all passed.
    """

    m: int
    expected_m: int
    count_ok: bool
    orthogonal_pairs: list
    min_pair_measure: float
    barycentre_gap: float
    barycentre_condition: float
    barycentre_error: float
    failures: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when every check passed."""
        return not self.failures

    def raise_for_failures(self) -> None:
        """Raise :class:`~flatserve.errors.BasisError` listing every failed check."""
        if self.failures:
            raise BasisError("basis check failed: " + "; ".join(self.failures))


class ScaleSelection(NamedTuple):
    """Result of :func:`select_scale`.

    Attributes
    ----------
    scale : float
        Smallest scale found whose chart round-trips ``>= fraction`` of the
        samples (or ``hi`` if even that does not).
    coverage : float
        Fraction of samples with status OK at ``scale``.
    reached : bool
        ``coverage >= fraction``.
    basis : Basis
        The basis at ``scale``.
    """

    scale: float
    coverage: float
    reached: bool
    basis: "Basis"


class Basis:
    """A basis of ``m`` flats of dimension ``k`` in R^d (paper Sec. 3).

    Parameters
    ----------
    Q : array_like, shape (m, d, d)
        Symmetric; need not be idempotent (tangent-simplex vertices are not).
    r : array_like, shape (m, d)
    k : int
        ``0 <= k < d``.
    require_flats : bool
        Validate (C1)/(C2) for every element.

    Attributes
    ----------
    Q : ndarray, shape (m, d, d)
    r : ndarray, shape (m, d)
    k, d, m : int
    dim : int
        ``(k+1)(d-k)``, the dimension of the manifold of k-flats; a full basis
        has ``m = dim + 1``.

    Examples
    --------
    >>> from flatserve import flats
    >>> Q, r = flats.from_rays([[0, 0], [0, 1], [1, 0]], [[1, 0], [1, 0.2], [1, -0.3]])
    >>> Basis(Q, r, k=1).check().ok
    True
    """

    def __init__(self, Q, r, k, *, require_flats: bool = False):
        Q = as_array(Q, "Q", ("m", None, None), min_rows=1)
        m, d, d2 = Q.shape
        if d < 1 or d2 != d:
            raise InvalidInputError(f"Q: expected shape (m, d, d), got {Q.shape}", "Q")
        r = as_array(r, "r", (m, d))
        k = _flats.check_k(k, d)
        if require_flats:
            _flats.validate(Q, r, k)
        elif np.abs(Q - np.swapaxes(Q, 1, 2)).max() > _flats.FLAT_TOL:
            raise InvalidInputError("Q: basis matrices must be symmetric", "Q")
        self.Q = Q
        self.r = r
        self.k = k
        self.d = d
        self.m = m
        self.dim = _flats.basis_size(k, d) - 1
        #: Set by :meth:`tangent_simplex`: centre flat (Q, r), scale, variant.
        self.center = None
        self.scale = None
        self.variant = None
        self.Q.setflags(write=False)
        self.r.setflags(write=False)

    def __repr__(self) -> str:
        return f"Basis(m={self.m}, k={self.k}, d={self.d})"

    # ----------------------------------------------------------------- constructors

    @classmethod
    def tangent_simplex(cls, center_Q, center_r, k, scale: float = 0.01,
                        variant: str = DEFAULT_VARIANT, frames=None) -> "Basis":
        """The quasi-regular base simplex of Sec. 5.1 around a centre flat.

        Parameters
        ----------
        center_Q : array_like, shape (d, d)
        center_r : array_like, shape (d,)
            A valid k-flat.
        k : int
        scale : float
            Multiple of the simplex (``S_4`` has edge ``2 sqrt(2)``).
        variant : {"tangent", "paper"}
            See the module docstring; ``DEFAULT_VARIANT`` keeps more samples.
        frames : tuple (A (d, k), N (d, d-k)), optional
            Spanning vectors and normals to use (their order and orientation
            orient the simplex).  Default: eigenvectors of ``center_Q``.

        Returns
        -------
        Basis
            ``m = (k+1)(d-k) + 1`` elements.
        """
        cQ = as_array(center_Q, "center_Q", (None, None))
        d = cQ.shape[0]
        cr = as_array(center_r, "center_r", (d,))
        k = _flats.check_k(k, d)
        _flats.validate(cQ[None], cr[None], k)
        if not (np.isfinite(scale) and scale > 0):
            raise InvalidInputError(f"scale: expected a positive number, got {scale!r}", "scale")
        if frames is None:
            A, N = _flats.frames(cQ[None], k)
            A, N = A[0], N[0]
        else:
            A = _orthonormal(as_array(frames[0], "frames", (d, k)), "frames")
            N = _orthonormal(as_array(frames[1], "frames", (d, d - k)), "frames")
            if np.abs(A.T @ N).max(initial=0.0) > 1e-8 or np.abs(N @ N.T - cQ).max() > 1e-8:
                raise InvalidInputError("frames: (A, N) do not match center_Q", "frames")
        alpha = N.T @ cr
        dQ, dr = tangent_directions(A, N, alpha, variant)
        S = simplex_vertices(dQ.shape[0])  # (D, D+1)
        Q = cQ[None] + scale * np.einsum("cl,cij->lij", S, dQ)
        r = cr[None] + scale * (S.T @ dr)
        B = cls(Q, r, k)
        B.center = (cQ.copy(), cr.copy())
        B.scale = float(scale)
        B.variant = variant
        return B

    @classmethod
    def around_axis(cls, axis: int = 2, d: int = 3, scale: float = 0.01,
                    variant: str = DEFAULT_VARIANT, offset=None) -> "Basis":
        """Tangent simplex of lines around a coordinate axis (the ray set-up).

        The centre is the line along ``e_axis`` through ``offset`` (default the
        origin); the normals are the other unit vectors in increasing order
        (around the z-axis: ``a = e_z``, ``n_1 = e_x``, ``n_2 = e_y``).

        Parameters
        ----------
        axis : int
            ``0 <= axis < d``.
        d : int
        scale : float
        variant : {"tangent", "paper"}
        offset : array_like, shape (d,), optional
            A point on the centre line.

        Returns
        -------
        Basis
            ``2(d-1) + 1`` lines (5 for ``d = 3``).
        """
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 2:
            raise InvalidInputError(f"d: expected an integer >= 2, got {d!r}", "d")
        if isinstance(axis, bool) or not isinstance(axis, (int, np.integer)) or not 0 <= axis < d:
            raise InvalidInputError(f"axis: expected an integer in [0, {d}), got {axis!r}", "axis")
        I = np.eye(d)
        A = I[:, [axis]]
        N = I[:, [i for i in range(d) if i != axis]]
        o = np.zeros(d) if offset is None else as_array(offset, "offset", (d,))
        cQ = N @ N.T
        cr = cQ @ o
        return cls.tangent_simplex(cQ, cr, 1, scale, variant, frames=(A, N))

    @staticmethod
    def default_center(k: int, d: int) -> tuple[np.ndarray, np.ndarray]:
        """The default centre flat: the span of the last ``k`` axes through the origin.

        For lines in R^3 the z-axis (the paper's ray set-up looks along it).

        Returns
        -------
        Q : ndarray, shape (d, d)
        r : ndarray, shape (d,)
        """
        k = _flats.check_k(k, d)
        A = np.eye(d)[:, d - k:]
        Q, r = _flats.from_parametric(A[None], np.zeros((1, d)))
        return Q[0], r[0]

    @property
    def is_full(self) -> bool:
        """``m == (k+1)(d-k) + 1`` (:func:`flatserve.flats.basis_size`)."""
        return self.m == _flats.basis_size(self.k, self.d)

    def require_full(self) -> "Basis":
        """Check that this basis can chart a field: full, and passing :meth:`check`.

        Returns
        -------
        Basis
            ``self``.

        Raises
        ------
        InvalidInputError
            ``"basis"``: the count is wrong or a check of Sec. 3 fails.
        """
        if not self.is_full:
            raise InvalidInputError(
                f"basis: a field needs m = (k+1)(d-k)+1 = {self.dim + 1} flats, got {self.m}",
                "basis")
        report = self.check()
        if not report.ok:
            raise InvalidInputError("basis: basis check failed: " + "; ".join(report.failures),
                                    "basis")
        return self

    # ---------------------------------------------------------------------- methods

    def combine(self, weights, gap_tol: float = _flats.GAP_TOL) -> _flats.Projection:
        """Projected affine combinations ``P(sum w_l q_l)`` (Eq. 4, 6).

        Parameters
        ----------
        weights : array_like, shape (n, m)
            Rows sum to one.

        Returns
        -------
        Projection
        """
        return _flats.affine_combination(weights, self.Q, self.r, self.k, gap_tol)

    def coordinates(self, Q, r, roundtrip_tol: float = _coords.ROUNDTRIP_TOL,
                    check: bool = True, native: bool | None = None) -> _coords.Coordinates:
        """Affine coordinates of targets (Fig. 8); see :func:`flatserve.coordinates.coordinates`.

        Parameters
        ----------
        Q : array_like, shape (n, d, d)
        r : array_like, shape (n, d)
        roundtrip_tol : float
        check : bool
            Validate the targets' (C1)/(C2).
        native : bool or None
            Use the native fast path for lines in R^3 (``None``: when built).

        Returns
        -------
        Coordinates
            ``weights (n, m)``, ``status (n,) int8``, ``residual (n,)``.
        """
        return _coords.coordinates(self.Q, self.r, self.k, Q, r, roundtrip_tol=roundtrip_tol,
                                   check=check, native=native)

    def coordinates_of(self, flats: _flats.Flats,
                       roundtrip_tol: float = _coords.ROUNDTRIP_TOL,
                       threads: int | None = None) -> _coords.Coordinates:
        """Coordinates of a :class:`~flatserve.flats.Flats` batch (validated when built).

        See :func:`flatserve.coordinates.coordinates_of`; rays take the fast path.

        Returns
        -------
        Coordinates
            ``weights (n, m)``, ``status (n,) int8``, ``residual (n,)``.
        """
        return _coords.coordinates_of(self.Q, self.r, self.k, flats, roundtrip_tol,
                                      threads=threads)

    def coordinates_rays(self, origins, directions,
                         roundtrip_tol: float = _coords.ROUNDTRIP_TOL,
                         threads: int | None = None) -> _coords.Coordinates:
        """Coordinates of lines given as origins + directions (``k = 1``).

        Uses the fast path of :func:`flatserve.coordinates.coordinates_rays`
        when available (``d = 3``), else the reference.

        Parameters
        ----------
        origins, directions : array_like, shape (n, d)
        roundtrip_tol : float
        threads : int, optional
            Threads of the native fast path (default: automatic); results do
            not depend on it.

        Returns
        -------
        Coordinates
        """
        if self.k != 1:
            raise InvalidInputError(f"origins: rays are lines, but this basis has k = {self.k}",
                                    "origins")
        return _coords.coordinates_rays(self.Q, self.r, origins, directions,
                                        roundtrip_tol=roundtrip_tol, threads=threads)

    def check(self, rcond: float = _coords.SINGULAR_RCOND,
              orthogonal_tol: float = ORTHOGONAL_TOL,
              probe_distance: float = PROBE_DISTANCE) -> BasisReport:
        """Run the checks of Sec. 3 that can be computed.

        1. right count: ``m == (k+1)(d-k) + 1``;
        2. no pair orthogonal (Sec. 3.1, Lemma 1);
        3. the barycentre ``P(sum q_l / m)`` is unambiguous, the coordinate
           system of Fig. 8 is non-singular there and returns ``w = 1/m``;
        4. the system is non-singular at the barycentre flat translated by
           ``probe_distance`` along each of its normals: a basis whose flats
           (nearly) coincide passes 3, which is scale-invariant, but charts
           nothing away from its centre.

        The Sec. 3.2 condition "no affine combination of m-1 elements is
        orthogonal to the remaining one" quantifies over a continuum and is
        not checked.

        Returns
        -------
        BasisReport
        """
        m, k = self.m, self.k
        failures = []
        expected = self.dim + 1
        count_ok = m == expected
        if not count_ok:
            failures.append(f"count: m = {m} flats, a basis of {k}-flats in R^{self.d} "
                            f"needs (k+1)(d-k)+1 = {expected}")
        iu, ju = np.triu_indices(m, 1)
        if iu.size:
            lam = np.linalg.eigvalsh(0.5 * (self.Q[iu] + self.Q[ju]))
            measure = 2.0 * np.abs(lam - 0.5).min(axis=1)
            bad = measure < orthogonal_tol
            pairs = [(int(a), int(b)) for a, b in zip(iu[bad], ju[bad])]
            min_measure = float(measure.min())
        else:
            pairs, min_measure = [], float("inf")
        if pairs:
            failures.append(f"orthogonal pairs {pairs[:10]} (Sec. 3.1): they span no "
                            "one-dimensional space")
        w0 = np.full((1, m), 1.0 / m)
        p = _flats.project_unchecked(np.einsum("nl,lij->nij", w0, self.Q), w0 @ self.r, k,
                                      _flats.GAP_TOL)
        gap = float(p.gap[0])
        if p.ambiguous[0]:
            failures.append(f"barycentre: eigen-gap {gap:.3g} below {_flats.GAP_TOL:g}, "
                            "projection ambiguous")
            cond, err = 0.0, float("inf")
        else:
            A, N = _flats.frames(p.Q, k)
            M = _coords.system_matrix(self.Q, self.r, A, N, p.r)
            H = regular_simplex(m) if m > 1 else np.zeros((1, 0))
            s = np.linalg.svd(M[:, :-1, :] @ H, compute_uv=False)[0]  # as in solve_system
            s = s if s.size else np.ones(1)
            cond = float(s[-1] / s[0]) if s[0] > 0 else 0.0
            if not cond > rcond:
                failures.append(f"barycentre: coordinate system singular "
                                f"(sigma_min/sigma_max = {cond:.3g})")
                err = float("inf")
            else:
                w, _ = _coords.solve_system(M, rcond)
                err = float(np.abs(w - w0).max())
                if count_ok and not err <= 1e-6:
                    failures.append(f"barycentre: recovered weights differ from 1/m by {err:.3g}")
            Nn = N[0].T  # (d-k, d) unit normals: translated flats (Q, r + t n)
            if Nn.size and count_ok:
                PQ = np.repeat(p.Q, Nn.shape[0], axis=0)
                Pr = p.r + probe_distance * Nn
                Pa, PN = _flats.frames(PQ, k)
                _, sing = _coords.solve_system(
                    _coords.system_matrix(self.Q, self.r, Pa, PN, Pr), rcond)
                if sing.any():
                    failures.append(
                        f"probes: the coordinate system is singular at flats {probe_distance:g} "
                        f"from the barycentre along {int(sing.sum())} of its {sing.size} normals "
                        "(basis flats nearly coincide: scale too small?)")
        return BasisReport(m, expected, count_ok, pairs, min_measure, gap, cond, err, failures)


#: A weight counts as non-negative (sample inside the simplex) when ``>= -CONVEX_TOL``.
CONVEX_TOL = 1e-12


def select_scale(Q, r, make_basis: Callable[[float], Basis], fraction: float = 0.99,
                 lo: float = 1e-4, hi: float = 1.0, rtol: float = 0.02,
                 max_iter: int = 60, inside: str = "convex") -> ScaleSelection:
    """Smallest basis scale that covers ``fraction`` of the samples (Sec. 5.1, bisection).

    A sample is covered when its coordinates round-trip (status OK) and, for
    ``inside="convex"`` (default), all its weights are ``>= -CONVEX_TOL``,
    i.e. it lies inside the simplex.

    Why the convex hull: the tangent simplex's vertices are
    ``centre + scale * S G`` (unprojected, as in the paper), so their *affine*
    hull is the same affine subspace of ``(Q, r)``-space for every scale, and
    so is the chart: round-trip coverage alone does not depend on the scale
    (measured: 98.27 % of the paper's rays from scale 1e-6 to 3).  What the
    scale changes is which samples fall inside the simplex: the weights are
    ``1/m + u / scale`` with ``u`` fixed per sample, so the convex coverage
    grows monotonically with the scale and bisection is exact.
    ``inside="affine"`` uses round-tripping only (then the answer is ``lo``
    whenever ``lo`` reaches the fraction).

    Parameters
    ----------
    Q : array_like, shape (n, d, d)
    r : array_like, shape (n, d)
        The sample flats (valid k-flats).
    make_basis : callable
        ``scale -> Basis``, e.g. ``lambda s: Basis.around_axis(2, scale=s)``.
    fraction : float
        Requested coverage in ``(0, 1]``.
    lo, hi : float
        Bracket, ``0 < lo < hi``.
    rtol : float
        Stop when ``hi / lo - 1 <= rtol``.
    max_iter : int
    inside : {"convex", "affine"}

    Returns
    -------
    ScaleSelection
        ``scale``, ``coverage`` reached, ``reached`` flag and the basis.  When
        even ``hi`` covers less than ``fraction``, ``hi`` is returned with
        ``reached = False``.

    Examples
    --------
    >>> from flatserve import flats
    >>> rng = np.random.default_rng(0)
    >>> o = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    >>> Q, r = flats.from_rays(o, np.c_[rng.uniform(-.3, .3, (500, 2)), np.ones(500)])
    >>> sel = select_scale(Q, r, lambda s: Basis.around_axis(2, scale=s), 0.9, hi=100.0)
    >>> sel.reached, sel.coverage >= 0.9
    (True, True)
    """
    Q = as_array(Q, "Q", ("n", None, None), min_rows=1)
    r = as_array(r, "r", (Q.shape[0], Q.shape[1]))
    if not 0 < fraction <= 1:
        raise InvalidInputError(f"fraction: expected 0 < fraction <= 1, got {fraction!r}",
                                "fraction")
    if not (0 < lo < hi and np.isfinite(hi)):
        raise InvalidInputError(f"lo: need 0 < lo < hi, got lo={lo!r}, hi={hi!r}", "lo")
    if inside not in ("convex", "affine"):
        raise InvalidInputError(f"inside: expected 'convex' or 'affine', got {inside!r}",
                                "inside")

    def coverage(scale):
        B = make_basis(scale)
        c = B.coordinates(Q, r, check=False)
        ok = c.status == _coords.OK
        if inside == "convex":
            ok &= c.weights.min(axis=1) >= -CONVEX_TOL
        return float(np.mean(ok)), B

    cov_hi, B_hi = coverage(hi)
    if cov_hi < fraction:
        return ScaleSelection(float(hi), cov_hi, False, B_hi)
    cov_lo, B_lo = coverage(lo)
    if cov_lo >= fraction:
        return ScaleSelection(float(lo), cov_lo, True, B_lo)
    for _ in range(max_iter):
        if hi / lo - 1.0 <= rtol:
            break
        mid = float(np.sqrt(lo * hi))
        cov, B = coverage(mid)
        if cov >= fraction:
            hi, cov_hi, B_hi = mid, cov, B
        else:
            lo = mid
    return ScaleSelection(float(hi), cov_hi, True, B_hi)
