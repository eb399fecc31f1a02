"""Isometric charts of lines in R^3: undo a tangent-simplex chart's stretch off its centre.

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
from .embedding import embed, row_product
from .errors import InvalidInputError
from .flats import Flats

__all__ = ["LineWarp", "CALIBRATION_DEG", "CALIBRATION_TOL"]

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
