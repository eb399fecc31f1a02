"""Isometric charts: undo a tangent-simplex chart's stretch off its centre (lines in
closed form, :class:`LineWarp`; k-flats of any k >= 1 by normal coordinates,
:class:`FlatWarp`).

A tangent-simplex chart (paper Sec. 5.1) of lines in R^3 is isometric at its
centre line (a shift of one unit of length and a turn of one radian move the
embedded point as far, in every direction: :class:`flatserve.atlas.Atlas`
``unit``) but not away from it.  Its embedded point (Sec. 5) splits into two
planes (measured, and tested in ``tests/test_warp.py``):

* a *turn* part ``T`` that depends only on the line's direction: at angle
  ``phi`` from the centre's axis, ``|T| = kT tan(2 phi) / 2`` towards the
  direction of the tilt (``tan(2 phi) = 2 t``, :mod:`flatserve.basis`);
* a *shift* part ``S``, linear in the line's offset for a fixed direction.

So a turn away from the centre is stretched by ``1 / cos^2(2 phi)`` (2.2 at 24
degrees), a turn about the centre's axis and a shift in the plane of the
tilt by ``cos(phi) / cos(2 phi)`` (1.4), a shift across it not at all.  The
chart's Delaunay cells then join samples far apart in one direction and close
in another, and a view interpolated in a chart whose centre is off its axis
loses against the same samples in a chart centred on it: 0.2-0.5 dB at 10
degrees, 1.4-1.5 dB at 24 (two bunny views, ``docs/orbit-results.md``).

:class:`LineWarp` maps a chart's embedded points ``x`` to ``y`` with
``|T_y| = kT phi`` (the angle itself) and the in-plane shift shrunk by
``cos(2 phi) / cos(phi)``.  The Jacobian of the warped chart, measured by
finite differences at lines through the centre's point up to 24 degrees off
its axis, has condition number at most 1.03 (the paper's chart: 2.23); at
offsets of one unit, 1.23 (against up to 4.4).  It is the identity to first
order at the centre, continuous and invertible on the chart's domain (below
45 degrees), and computed row by row in a fixed order (a line's point does not
depend on its batch).  Lines in R^d have the same structure with a turn
part and a shift part of d - 1 coordinates each (measured by finite
differences for d = 4: the same condition numbers as in R^3, turn by turn
and shift by shift, ``tests/test_warp.py``), and :class:`LineWarp` warps
them alike; atlases of lines in R^3 are isometric by default, others opt in
(:class:`flatserve.atlas.Atlas` ``isometric``).

Any k-flats: :class:`FlatWarp` takes an embedded point back to its flat (the
chart's affine combination) and gives it :func:`normal_coordinates` about the
chart's centre (the log map of the Grassmannian: the principal angles towards
their turns, in radians; the offset carried along the geodesic), times the
chart's Jacobian at its centre, so that it too is the identity to first order
at the centre. Against the principal angles of nearby flats (the
Grassmannian's own distance) the warped chart measures a turn within 1 and
``r / sin(r)`` (the curvature) up to 40 degrees, where the paper's chart
stretches it 2-4x (``tests/test_warp.py``). Measured in
``benchmarks/accuracy_by_kind.py`` (``docs/costs.md``): one chart's error is
flatter across it (planes in R^3: 1.7x from the centre to its edge against
3.5x), but in an atlas the isometric charts answer fewer queries in 6
dimensions (79 % for planes in R^4 at 3,000 samples), so they are an opt-in
for every kind but lines in R^3.

Example
-------
>>> import numpy as np, flatserve
>>> from flatserve.warp import LineWarp
>>> basis = flatserve.Basis.around_axis(axis=2, scale=1.0)
>>> warp = LineWarp.calibrate(basis)
>>> f = flatserve.Field(basis, warp=warp)
>>> f.chart(flatserve.Flats.from_rays([[0, 0, 0.0]], [[0, 0, 1.0]])).points.shape
(1, 4)
"""
from __future__ import annotations

import math

import numpy as np

from .coordinates import OK
from .embedding import embed, row_product, unembed
from .errors import InvalidInputError
from .flats import Flats, project_unchecked

__all__ = ["LineWarp", "FlatWarp", "normal_coordinates", "warp_from_dict", "CALIBRATION_DEG",
           "CALIBRATION_TOL", "CALIBRATION_STEP"]

#: The tilt (degrees) of the calibration line that measures ``kT``; any angle
#: below 45 gives the same ``kT`` up to rounding (``|T| = kT tan(2 phi) / 2``).
CALIBRATION_DEG = 10.0
#: Round-trip tolerance of the calibration lines, per unit of the centre's
#: distance from the origin (at least 1): the warp needs their points, not
#: the field's trust, and far from the origin a chart's rounding reaches the
#: field's tolerance (2.8e-6 at distance 1000) on lines it holds.
CALIBRATION_TOL = 1e-6
#: How far from orthonormal a stored frame may be (:meth:`LineWarp.from_dict`).
FRAME_TOL = 1e-9
#: The step (radians of turn, units of shift) of :meth:`FlatWarp.calibrate`'s
#: central differences (their error is of the order of its square).
CALIBRATION_STEP = 1e-4


class LineWarp:
    """The warp of one tangent-simplex chart of lines in R^d (module docstring).

    Parameters
    ----------
    origin : ndarray, shape (2(d-1),)
        The embedded point of the chart's centre line.
    frame : ndarray, shape (2(d-1), 2(d-1))
        Rows: unit vectors of the turn subspace (d - 1) and of the shift
        subspace (d - 1), paired (a tilt towards a direction and a shift
        along it).
    kT : float
        ``|T| = kT tan(2 phi) / 2``.

    Use :meth:`calibrate` to build one from a basis.
    """

    def __init__(self, origin, frame, kT: float):
        self.origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1)
        n = self.origin.shape[0]
        if n < 2 or n % 2:
            raise InvalidInputError(f"warp: expected an origin of 2(d-1) coordinates, got {n}",
                                    "warp")
        self.frame = np.ascontiguousarray(frame, dtype=np.float64).reshape(n, n)
        self.kT = float(kT)
        if not (np.isfinite(self.origin).all() and np.isfinite(self.frame).all()
                and math.isfinite(self.kT) and self.kT > 0):
            raise InvalidInputError("warp: expected a finite origin, frame and kT > 0", "warp")
        off = float(np.abs(self.frame @ self.frame.T - np.eye(n)).max())
        if off > FRAME_TOL:
            raise InvalidInputError(f"warp: the frame is not orthonormal (off by {off:.3g})",
                                    "warp")
        # orthonormal by construction (calibrate); its transpose is its inverse
        self._FT = np.ascontiguousarray(self.frame.T)

    @property
    def ndim(self) -> int:
        """The dimension of the chart's embedded points, 2(d-1)."""
        return self.origin.shape[0]

    @classmethod
    def calibrate(cls, basis, *, calibration_tol: float = CALIBRATION_TOL,
                  calibration_deg: float = CALIBRATION_DEG) -> "LineWarp":
        """The warp of the chart of ``basis`` (a tangent simplex of lines in R^d).

        Measures the chart on 2d - 1 lines: its centre, the centre tilted by
        ``calibration_deg`` towards d - 1 orthogonal directions about the
        centre's point, and the centre shifted along them.

        Parameters
        ----------
        basis : flatserve.Basis
            With ``basis.center`` set (a tangent simplex), k = 1, d >= 2.
        calibration_tol : float
            Round-trip tolerance of the calibration lines per unit of the
            centre's distance from the origin (:data:`CALIBRATION_TOL`).
        calibration_deg : float
            Tilt of the calibration lines (degrees, in (0, 45)).

        Returns
        -------
        LineWarp
        """
        if basis.k != 1 or basis.d < 2 or basis.center is None:
            raise InvalidInputError("warp: only tangent-simplex charts of lines have one",
                                    "warp")
        Qc, rc = basis.center
        _, V = np.linalg.eigh(np.asarray(Qc, dtype=np.float64))
        axis, ns = V[:, 0], V[:, 1:].T  # Q = I - a a^T: eigenvalue 0 along a
        p = np.asarray(rc, dtype=np.float64)  # the centre's point closest to the origin
        ph = math.radians(calibration_deg)
        tilts = [math.cos(ph) * axis + math.sin(ph) * n for n in ns]
        o = np.stack([p] * (1 + len(ns)) + [p + n for n in ns])
        d = np.stack([axis, *tilts] + [axis] * len(ns))
        tol = calibration_tol * max(1.0, float(np.linalg.norm(p)))
        co = basis.coordinates_of(Flats.from_rays(o, d), tol)
        if not (np.asarray(co.status) == OK).all():
            raise InvalidInputError(
                f"warp: the chart does not hold its calibration lines (round trip within {tol:g}; "
                "a collapsed chart: its scale?)", "warp")
        x = embed(co.weights)
        c0 = x[0]
        cols = x[1:] - c0
        kT = float(np.linalg.norm(cols[0])) / (math.tan(2 * ph) / 2)
        frame = cols / np.linalg.norm(cols, axis=1, keepdims=True)
        # the turn and shift subspaces are orthogonal and each pair is orthonormal
        # (measured for d = 3 and 4; re-orthonormalised so that the frame is a
        # rotation to the last bit)
        q, rr = np.linalg.qr(frame.T)
        frame = (q * np.sign(np.diag(rr))).T
        return cls(c0, frame, kT)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Warp embedded points: (n, 2(d-1)) -> (n, 2(d-1)), row by row (module docstring)."""
        x = np.asarray(x, dtype=np.float64)
        D = self.ndim
        if x.shape[0] == 0:
            return np.empty((0, D))
        y = row_product(x - self.origin, self._FT)
        h = D // 2
        T, S = y[:, :h], y[:, h:]
        nT = np.sqrt(np.einsum("ij,ij->i", T, T))
        t2 = nT * (2.0 / self.kT)  # tan(2 phi)
        c2 = 1.0 / np.sqrt(1.0 + t2 * t2)  # cos(2 phi)
        # f = phi / t (the turn's new length over its old), g = cos(2 phi) / cos(phi) - 1
        f = np.ones_like(nT)
        np.divide(np.arctan(t2), t2, out=f, where=t2 > 1e-8)
        g = c2 / np.sqrt(0.5 + 0.5 * c2) - 1.0
        # the shift along the tilt's direction (T / |T|) times g: g (S.T) T / |T|^2
        inv = np.zeros_like(nT)
        np.divide(g, nT * nT, out=inv, where=t2 > 1e-8)
        hh = np.einsum("ij,ij->i", S, T) * inv
        S += hh[:, None] * T
        T *= f[:, None]
        out = row_product(y, self.frame)
        out += self.origin
        return out

    # --------------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        """JSON-able (floats round-trip exactly); :meth:`from_dict` inverts it.
        Lines in R^3 keep the kind ``"lines3"`` they were stored with before
        other dimensions had warps."""
        return {"kind": "lines3" if self.ndim == 4 else "lines", "origin": self.origin.tolist(),
                "frame": self.frame.tolist(), "kT": self.kT}

    @classmethod
    def from_dict(cls, spec: dict) -> "LineWarp":
        kind = spec.get("kind")
        if kind not in ("lines3", "lines"):
            raise InvalidInputError(f"warp: unknown kind {kind!r}", "warp")
        w = cls(np.array(spec["origin"]), np.array(spec["frame"]), spec["kT"])
        if (kind == "lines3") != (w.ndim == 4):
            raise InvalidInputError(f"warp: kind {kind!r} with {w.ndim} coordinates", "warp")
        return w

    def __repr__(self) -> str:
        return f"LineWarp(kT={self.kT:.6g})"


# ---------------------------------------------------------------------- any (k, d)
def normal_coordinates(P, r, center_A, center_N, point) -> np.ndarray:
    """Normal coordinates of k-flats about a centre flat: the log map of the
    Grassmannian and the offset, carried along the geodesic.

    The direction space ``U`` of a flat is ``U = exp(H)`` of the centre's
    ``U0``: ``H`` ((d-k) x k, in the centre's normals ``N0`` and spanning
    vectors ``U0``) has the principal angles between the two as its singular
    values, each towards the direction of its turn (``N0^T U (U0^T U)^-1 =
    Qs tan(S) V^T``, ``H = Qs S V^T``). The offset is the flat's point closest to
    the centre's ``point`` minus that point, in the centre's normals turned
    with the flat (the rotation ``exp(N0 H U0^T - U0 H^T N0^T)``, which takes
    ``U0`` to ``U``). A turn of one radian and a shift of one unit of length
    move the coordinates as far, in every direction, at every flat up to the
    Grassmannian's curvature (a turn across the radius ``r`` moves them
    ``r / sin(r)`` times too far at most: 1.09 at 40 degrees, 1.18 where the
    curvature is 2, as for planes in R^4; ``tests/test_warp.py`` measures it
    against the principal angles).

    Parameters
    ----------
    P : ndarray, shape (n, d, d)
        The flats' direction projectors ``I - Q`` (valid flats, (C1)).
    r : ndarray, shape (n, d)
        Their points closest to the origin (Eq. 3).
    center_A : ndarray, shape (d, k)
    center_N : ndarray, shape (d, d - k)
        The centre's orthonormal spanning vectors and normals.
    point : ndarray, shape (d,)
        A point of the centre flat.

    Returns
    -------
    ndarray, shape (n, (k + 1)(d - k))
        ``H`` row by row, then the offset's ``d - k`` coordinates. Each row
        depends only on its own flat: every product is a stack of one flat's
        small matrices (never one matrix product over the batch, which BLAS
        may round differently with other rows beside it).

    Examples
    --------
    >>> import numpy as np
    >>> A0, N0 = np.eye(3)[:, 2:], np.eye(3)[:, :2]
    >>> th = 0.3                                  # the z-axis tilted towards x, then shifted in y
    >>> u = np.array([np.sin(th), 0, np.cos(th)])
    >>> P = np.outer(u, u)[None]
    >>> z = normal_coordinates(P, np.array([[0.0, 2.0, 0.0]]), A0, N0, np.zeros(3))
    >>> np.round(z, 12).tolist()
    [[0.3, 0.0, 0.0, 2.0]]
    """
    n = P.shape[0]
    A0, N0 = center_A, center_N
    k, dk = A0.shape[1], N0.shape[1]
    PA = np.matmul(P, A0)                                   # (n, d, k): U U^T U0
    M = np.matmul(A0.T, PA)                                 # (n, k, k): U0^T P U0
    B = np.matmul(N0.T, PA)                                 # (n, d-k, k)
    T = np.swapaxes(np.linalg.solve(M, np.swapaxes(B, 1, 2)), 1, 2)  # B M^-1 = tan
    Qs, S, Vt = np.linalg.svd(T, full_matrices=False)
    sig = np.arctan(S)                                      # the principal angles
    H = np.matmul(Qs * sig[:, None, :], Vt)
    o = r - point - np.matmul(P, (r - point)[:, :, None])[:, :, 0]  # closest point - point
    bN = np.matmul(o[:, None, :], N0)[:, 0, :]              # (n, d-k)
    aU = np.matmul(o[:, None, :], A0)[:, 0, :]              # (n, k)
    b = np.matmul(bN[:, None, :], Qs)[:, 0, :]              # q_i . N0^T o
    a = np.matmul(Vt, aU[:, :, None])[:, :, 0]              # v_i . U0^T o
    oc = bN + np.matmul(Qs, ((np.cos(sig) - 1.0) * b - np.sin(sig) * a)[:, :, None])[:, :, 0]
    return np.concatenate([H.reshape(n, dk * k), oc], axis=1)


class FlatWarp:
    """The isometric warp of one tangent-simplex chart of k-flats in R^d (any k >= 1).

    The chart's embedded point ``x`` is taken back to its flat (the paper's
    affine combination of the chart's basis, Eq. 4, 6), whose
    :func:`normal_coordinates` ``z`` about the chart's centre go through the
    chart's own Jacobian at its centre ``J = dx/dz`` (measured by central
    differences, :meth:`calibrate`): ``y = x0 + J z``. So the warped chart is
    the identity to first order at its centre, and off it measures turns and
    shifts as at its centre (a tangent-simplex chart stretches a turn
    towards its edge: by ``1/cos^2(2 phi)`` for lines, 2-3x at 40 degrees for
    planes in R^3 and R^4). Lines have :class:`LineWarp`, the same map in closed
    form.

    Parameters
    ----------
    Q : ndarray, shape (m, d, d)
    r : ndarray, shape (m, d)
        The chart's basis (:class:`flatserve.Basis`).
    k : int
    center_A : ndarray, shape (d, k)
    center_N : ndarray, shape (d, d - k)
    point : ndarray, shape (d,)
        The centre flat: orthonormal spanning vectors, normals, a point.
    origin : ndarray, shape (m - 1,)
        The centre's embedded point.
    J : ndarray, shape (m - 1, m - 1)
        The chart's Jacobian at its centre, columns along ``z``.

    Use :meth:`calibrate` to build one from a basis.

    Examples
    --------
    >>> import flatserve
    >>> Q, r = flatserve.Basis.default_center(2, 3)
    >>> basis = flatserve.Basis.tangent_simplex(Q, r, 2, scale=1.0)
    >>> warp = FlatWarp.calibrate(basis)
    >>> f = flatserve.Field(basis, warp=warp)
    >>> pl = flatserve.Flats.from_parametric([[[1.0, 0], [0, 0.9], [0, 0.3]]], [[0, 0, 0.5]])
    >>> f.chart(pl).points.shape
    (1, 3)
    """

    def __init__(self, Q, r, k: int, center_A, center_N, point, origin, J):
        self.Q = np.ascontiguousarray(Q, dtype=np.float64)
        self.r = np.ascontiguousarray(r, dtype=np.float64)
        self.k = int(k)
        self.center_A = np.ascontiguousarray(center_A, dtype=np.float64)
        self.center_N = np.ascontiguousarray(center_N, dtype=np.float64)
        self.point = np.ascontiguousarray(point, dtype=np.float64).reshape(-1)
        self.origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1)
        m, d = self.Q.shape[0], self.point.shape[0]
        D = m - 1
        self.J = np.ascontiguousarray(J, dtype=np.float64)
        shapes = {"Q": (self.Q.shape, (m, d, d)), "r": (self.r.shape, (m, d)),
                  "center_A": (self.center_A.shape, (d, self.k)),
                  "center_N": (self.center_N.shape, (d, d - self.k)),
                  "origin": (self.origin.shape, (D,)), "J": (self.J.shape, (D, D))}
        for name, (got, want) in shapes.items():
            if got != want:
                raise InvalidInputError(f"warp: {name}: expected shape {want}, got {got}", "warp")
        if not 1 <= self.k < d or D != (self.k + 1) * (d - self.k):
            raise InvalidInputError(f"warp: {m} basis flats for {self.k}-flats in R^{d}", "warp")
        arrays = (self.Q, self.r, self.center_A, self.center_N, self.point, self.origin, self.J)
        if not all(np.isfinite(a).all() for a in arrays):
            raise InvalidInputError("warp: expected finite arrays", "warp")
        C = np.concatenate([self.center_A, self.center_N], axis=1)
        off = float(np.abs(C.T @ C - np.eye(d)).max())
        if off > FRAME_TOL:
            raise InvalidInputError(f"warp: the centre's frame is not orthonormal (off by "
                                    f"{off:.3g})", "warp")
        if np.linalg.cond(self.J) > 1e8:
            raise InvalidInputError("warp: a singular Jacobian (a collapsed chart: its scale?)",
                                    "warp")
        self._JT = np.ascontiguousarray(self.J.T)

    @property
    def ndim(self) -> int:
        """The dimension of the chart's embedded points, (k + 1)(d - k)."""
        return self.origin.shape[0]

    @classmethod
    def calibrate(cls, basis, *, calibration_tol: float = CALIBRATION_TOL,
                  step: float = CALIBRATION_STEP) -> "FlatWarp":
        """The warp of the chart of ``basis`` (a tangent simplex, k >= 1).

        Measures the chart at its centre and at the flats one ``step`` away
        along each normal coordinate, both ways (each spanning vector of the
        centre turned towards each normal; the centre shifted along each
        normal): ``J`` by central differences.

        Parameters
        ----------
        basis : flatserve.Basis
            With ``basis.center`` set (a tangent simplex), 1 <= k < d.
        calibration_tol : float
            Round-trip tolerance of the calibration flats per unit of the
            centre's distance from the origin (:data:`CALIBRATION_TOL`).
        step : float
            Radians of turn and units of shift (:data:`CALIBRATION_STEP`).

        Returns
        -------
        FlatWarp
        """
        k, d = basis.k, basis.d
        if k < 1 or basis.center is None:
            raise InvalidInputError("warp: only tangent-simplex charts of flats with k >= 1 "
                                    "have one", "warp")
        Qc, rc = basis.center
        _, V = np.linalg.eigh(np.asarray(Qc, dtype=np.float64))
        A0, N0 = V[:, :k], V[:, k:]
        p0 = np.asarray(rc, dtype=np.float64)
        A, b = [A0], [p0]
        for sgn in (1.0, -1.0):
            h = sgn * step
            for a in range(d - k):          # turns: z's H row by row
                for j in range(k):
                    U = A0.copy()
                    U[:, j] = math.cos(h) * A0[:, j] + math.sin(h) * N0[:, a]
                    A.append(U)
                    b.append(p0)
            for a in range(d - k):          # shifts
                A.append(A0)
                b.append(p0 + h * N0[:, a])
        tol = calibration_tol * max(1.0, float(np.linalg.norm(p0)))
        co = basis.coordinates_of(Flats.from_parametric(np.stack(A), np.stack(b)), tol)
        if not (np.asarray(co.status) == OK).all():
            raise InvalidInputError(
                f"warp: the chart does not hold its calibration flats (round trip within "
                f"{tol:g}; a collapsed chart: its scale?)", "warp")
        x = embed(co.weights)
        D = x.shape[1]
        J = (x[1:1 + D] - x[1 + D:]).T / (2.0 * step)
        return cls(basis.Q, basis.r, k, A0, N0, p0, x[0], J)

    def normal(self, x: np.ndarray) -> np.ndarray:
        """The :func:`normal_coordinates` of the flats of embedded points ``x``
        (n, m - 1): their flats by the chart's affine combination (Eq. 4, 6)."""
        x = np.asarray(x, dtype=np.float64)
        m, d = self.Q.shape[0], self.point.shape[0]
        if not len(x):
            return np.empty((0, m - 1))
        w = unembed(x)
        Qs = row_product(w, self.Q.reshape(m, d * d)).reshape(-1, d, d)
        Qs = 0.5 * (Qs + np.swapaxes(Qs, 1, 2))
        rs = row_product(w, self.r)
        pr = project_unchecked(Qs, rs, self.k)
        return normal_coordinates(np.eye(d) - pr.Q, pr.r, self.center_A, self.center_N,
                                  self.point)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Warp embedded points: (n, m - 1) -> (n, m - 1), row by row."""
        x = np.asarray(x, dtype=np.float64)
        if not len(x):
            return np.empty((0, self.ndim))
        return row_product(self.normal(x), self._JT) + self.origin

    # --------------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        """JSON-able (floats round-trip exactly); :func:`warp_from_dict` inverts it."""
        return {"kind": "flats", "k": self.k, "Q": self.Q.tolist(), "r": self.r.tolist(),
                "center_A": self.center_A.tolist(), "center_N": self.center_N.tolist(),
                "point": self.point.tolist(), "origin": self.origin.tolist(),
                "J": self.J.tolist()}

    @classmethod
    def from_dict(cls, spec: dict) -> "FlatWarp":
        if spec.get("kind") != "flats":
            raise InvalidInputError(f"warp: unknown kind {spec.get('kind')!r}", "warp")
        return cls(*(np.array(spec[key], dtype=np.float64) for key in ("Q", "r")), int(spec["k"]),
                   *(np.array(spec[key], dtype=np.float64)
                     for key in ("center_A", "center_N", "point", "origin", "J")))

    def __repr__(self) -> str:
        return f"FlatWarp(k={self.k}, d={self.point.shape[0]})"


def warp_from_dict(spec: dict) -> "LineWarp | FlatWarp":
    """A warp stored by ``to_dict`` (:class:`LineWarp` or :class:`FlatWarp`).

    Raises
    ------
    flatserve.errors.InvalidInputError
        ``"warp"``: an unknown kind, or arrays that do not describe a warp.
    """
    if not isinstance(spec, dict):
        raise InvalidInputError("warp: expected an object", "warp")
    if spec.get("kind") == "flats":
        return FlatWarp.from_dict(spec)
    return LineWarp.from_dict(spec)
