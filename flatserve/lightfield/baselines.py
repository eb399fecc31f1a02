"""Baselines on the same samples and views as the field.

* :class:`TwoPlane`: the classic two-plane light-field parameterisation (a
  ray is its intersections with two parallel planes, 4 numbers),
  interpolated with :class:`scipy.interpolate.LinearNDInterpolator`
  (Delaunay in R^4, barycentric blending).
* :class:`NearestEmbedded`: the value of the nearest sample in the embedded
  basis coordinates (the same points the field triangulates), via
  :class:`scipy.spatial.cKDTree`.

Neither is tuned beyond its natural defaults, and neither is the field.
"""
from __future__ import annotations

import time

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import DEFAULT_EYE

__all__ = ["TwoPlane", "NearestEmbedded", "PARALLEL_TOL", "TWO_PLANE_Z"]

#: The two planes: the sampling screen (z = 0) and the plane through the
#: centre of the eye box (z = -3), the natural "camera" and "focal" planes of
#: the paper's set-up.
TWO_PLANE_Z = (0.0, float(DEFAULT_EYE[2]))
#: Rays whose direction has |dz| below this (relative to its length) do not
#: cross the planes.
PARALLEL_TOL = 1e-9


def two_plane_coordinates(origins, directions, planes=TWO_PLANE_Z) -> np.ndarray:
    """Two-plane parameters (s, t, u, v) of rays.

    Parameters
    ----------
    origins, directions : (n, 3) float
    planes : (float, float)
        z of the two planes.

    Returns
    -------
    (n, 4) float64
        (x, y) at the first plane, (x, y) at the second; NaN for rays parallel
        to the planes.
    """
    o = as_array(origins, "origins", (None, 3))
    d = as_array(directions, "directions", (o.shape[0], 3))
    dz = d[:, 2]
    par = np.abs(dz) <= PARALLEL_TOL * np.linalg.norm(d, axis=1)
    dz = np.where(par, 1.0, dz)
    out = []
    for z in planes:
        t = (z - o[:, 2]) / dz
        out.append(o[:, :2] + t[:, None] * d[:, :2])
    st = np.concatenate(out, axis=1)
    st[par] = np.nan
    return st


class TwoPlane:
    """Two-plane light field with scipy's piecewise-linear interpolation.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays.
    values : (n, C) float
        Their colours.
    planes : (float, float)
        z of the two planes.

    Attributes
    ----------
    build_seconds : float
        Time of scipy's Delaunay triangulation (in the constructor).
    """

    def __init__(self, origins, directions, values, planes=TWO_PLANE_Z):
        from scipy.interpolate import LinearNDInterpolator

        st = two_plane_coordinates(origins, directions, planes)
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 1:
            values = values[:, None]
        values = as_array(values, "values", (st.shape[0], None))
        keep = np.all(np.isfinite(st), axis=1)
        if keep.sum() < 6:
            raise InvalidInputError("origins: need at least 6 rays that cross the planes", "origins")
        self.planes = tuple(float(z) for z in planes)
        t0 = time.perf_counter()
        self._interp = LinearNDInterpolator(st[keep], values[keep], fill_value=np.nan)
        self._interp.tri.transform  # scipy computes the barycentric transforms lazily: count them here
        self.build_seconds = time.perf_counter() - t0
        self.nsamples = int(keep.sum())

    def __call__(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate rays.

        Returns
        -------
        values : (q, C) float64
            NaN outside the samples' hull.
        inside : (q,) bool
        """
        st = two_plane_coordinates(origins, directions, self.planes)
        ok = np.all(np.isfinite(st), axis=1)
        C = self._interp.values.shape[1]
        out = np.full((st.shape[0], C), np.nan)
        if ok.any():
            out[ok] = self._interp(st[ok]).reshape(-1, C)
        inside = np.all(np.isfinite(out), axis=1)
        return out, inside


class NearestEmbedded:
    """Nearest sample in the embedded basis coordinates (a k-d tree).

    Parameters
    ----------
    points : (n, D) float
        Embedded coordinates of the samples (e.g. ``field.points``).
    values : (n, C) float

    Attributes
    ----------
    build_seconds : float
    """

    def __init__(self, points, values):
        from scipy.spatial import cKDTree

        self.points = as_array(points, "points", (None, None), min_rows=1)
        v = np.asarray(values, dtype=np.float64)
        self.values = as_array(v[:, None] if v.ndim == 1 else v, "values", (self.points.shape[0], None))
        t0 = time.perf_counter()
        self._tree = cKDTree(self.points)
        self.build_seconds = time.perf_counter() - t0

    @classmethod
    def from_field(cls, field) -> "NearestEmbedded":
        """The samples a :class:`flatserve.Field` triangulates."""
        return cls(field.points, field.values)

    def __call__(self, x, workers: int = -1) -> np.ndarray:
        """Values of the nearest samples to embedded query points ``x`` (q, D) -> (q, C)."""
        x = as_array(x, "x", (None, self.points.shape[1]))
        if x.shape[0] == 0:
            return np.empty((0, self.values.shape[1]))
        _, idx = self._tree.query(x, k=1, workers=workers)
        return self.values[idx]
