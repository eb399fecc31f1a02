"""Baselines on the same samples and views as the field.

* :class:`TwoPlane`: the classic two-plane light-field parameterisation (a
  ray is its intersections with two parallel planes, 4 numbers),
  interpolated with :class:`scipy.interpolate.LinearNDInterpolator`
  (Delaunay in R^4, barycentric blending).
* :class:`NearestEmbedded`: the value of the nearest sample in the embedded
  basis coordinates (the same points the field triangulates), via
  :class:`scipy.spatial.cKDTree`.
* :class:`TwoPlaneNearest`: the two-plane parameterisation's ``k`` nearest
  sample rays, inverse-distance weighted (the classic baseline of
  forward-facing captures).
* :class:`TwoSphere`: for unstructured 360-degree data, the two-sphere
  parameterisation (a ray is its entry and exit points on a bounding sphere,
  6 numbers; a ray and its reverse swap them, so it is oriented), the ``k``
  nearest sample rays in it (:class:`scipy.spatial.cKDTree`), inverse-distance
  weighted.

Neither is tuned beyond its natural defaults, and neither is the field.
"""
from __future__ import annotations

import time

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import DEFAULT_EYE, ORBIT_RADIUS

__all__ = ["TwoPlane", "TwoPlaneNearest", "NearestEmbedded", "TwoSphere", "two_sphere_coordinates", "PARALLEL_TOL",
           "TWO_PLANE_Z", "TWO_SPHERE_K", "IDW_POWER"]

#: The two planes: the sampling screen (z = 0) and the plane through the
#: centre of the eye box (z = -3), the natural "camera" and "focal" planes of
#: the paper's set-up.
TWO_PLANE_Z = (0.0, float(DEFAULT_EYE[2]))
#: Rays whose direction has |dz| below this (relative to its length) do not
#: cross the planes.
PARALLEL_TOL = 1e-9


#: Neighbours of the two-sphere baseline: the number of samples the field's
#: interpolant blends (the D + 1 = 5 vertices of a simplex of the
#: 4-dimensional embedding of lines in R^3), so that both answers are weighted
#: means of 5 sample values.
TWO_SPHERE_K = 5
#: Inverse-distance weights ``1 / distance**IDW_POWER``: Shepard's classic 2.
IDW_POWER = 2.0


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


class _NearestRays:
    """The ``k`` nearest sample rays in some parameterisation, inverse-distance weighted."""

    def _build(self, x: np.ndarray, values, k, power, what: str) -> None:
        """A k-d tree over the samples' parameters ``x`` (n, p); NaN rows (rays that do not
        ``what``) are left out."""
        from scipy.spatial import cKDTree

        v = np.asarray(values, dtype=np.float64)
        v = as_array(v[:, None] if v.ndim == 1 else v, "values", (x.shape[0], None))
        if not (isinstance(k, (int, np.integer)) and k >= 1):
            raise InvalidInputError(f"k: expected a positive integer, got {k!r}", "k")
        if not (np.isfinite(power) and power > 0):
            raise InvalidInputError(f"power: expected a positive number, got {power!r}", "power")
        keep = np.isfinite(x).all(axis=1)
        if keep.sum() < k:
            raise InvalidInputError(f"origins: need at least k = {k} rays that {what}, "
                                    f"got {int(keep.sum())}", "origins")
        self.k, self.power = int(k), float(power)
        self.values = v[keep]
        t0 = time.perf_counter()
        self._tree = cKDTree(x[keep])
        self.build_seconds = time.perf_counter() - t0
        self.nsamples = int(keep.sum())

    def _answer(self, x: np.ndarray, workers: int) -> tuple[np.ndarray, np.ndarray]:
        return _idw(self._tree, x, self.values, self.k, self.power, workers)


def _idw(tree, x, values, k: int, power: float, workers: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest samples of ``tree`` to each finite row of ``x``, inverse-distance
    weighted (``1 / dist**power``; a sample at distance 0 gives its own value).

    Returns values (q, C), NaN for rows of ``x`` that are not finite, and which rows are."""
    ok = np.isfinite(x).all(axis=1)
    C = values.shape[1]
    out = np.full((x.shape[0], C), np.nan)
    if ok.any():
        dist, idx = tree.query(x[ok], k=k, workers=workers)
        dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
        exact = dist[:, 0] == 0
        with np.errstate(divide="ignore"):
            w = 1.0 / dist ** power
        w[exact] = 0.0
        w[exact, 0] = 1.0
        out[ok] = np.einsum("qk,qkc->qc", w, values[idx]) / w.sum(axis=1)[:, None]
    return out, ok


def two_sphere_coordinates(origins, directions, center=(0.0, 0.0, 0.0),
                           radius: float = ORBIT_RADIUS) -> np.ndarray:
    """Two-sphere parameters of rays: entry and exit points on a sphere.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Rays (directions need not be unit).
    center : (3,) float
    radius : float
        The bounding sphere.

    Returns
    -------
    (n, 6) float64
        The first point where the ray's line enters the sphere, then where it
        leaves it (in the direction of travel; a reversed ray swaps them);
        NaN for lines that miss the sphere (tangent lines count as hitting).
    """
    o = as_array(origins, "origins", (None, 3))
    d = as_array(directions, "directions", (o.shape[0], 3))
    c = as_array(center, "center", (3,))
    if not (np.isfinite(radius) and radius > 0):
        raise InvalidInputError(f"radius: expected a positive number, got {radius!r}", "radius")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not (norm > 0).all():
        raise InvalidInputError("directions: expected non-zero directions", "directions")
    u = d / norm
    oc = o - c
    b = np.einsum("ij,ij->i", oc, u)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius * radius)
    root = np.sqrt(np.where(disc >= 0, disc, 0.0))
    out = np.concatenate([oc + (-b - root)[:, None] * u, oc + (-b + root)[:, None] * u], axis=1) + np.tile(c, 2)
    out[disc < 0] = np.nan
    return out


class TwoSphere(_NearestRays):
    """k nearest sample rays in the two-sphere parameterisation, inverse-distance weighted.

    A query ray's value is ``sum_i w_i v_i / sum_i w_i`` over its ``k``
    nearest samples in R^6 (:func:`two_sphere_coordinates`), ``w_i = 1 /
    dist_i**power``; a sample at distance 0 gives its own value.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays (at least ``k`` of them must meet the sphere).
    values : (n, C) float, or (n,)
    center : (3,) float
    radius : float
        The bounding sphere (default: the ball the 360-degree samples are
        drawn through, :data:`~flatserve.lightfield.camera.ORBIT_RADIUS`).
    k : int
        Neighbours (:data:`TWO_SPHERE_K`).
    power : float
        Of the inverse distance (:data:`IDW_POWER`).

    Attributes
    ----------
    build_seconds : float
        Time of the k-d tree.
    nsamples : int
        Samples that meet the sphere (the others are left out).
    """

    def __init__(self, origins, directions, values, center=(0.0, 0.0, 0.0),
                 radius: float = ORBIT_RADIUS, k: int = TWO_SPHERE_K, power: float = IDW_POWER):
        x = two_sphere_coordinates(origins, directions, center, radius)
        self.center = np.asarray(center, dtype=np.float64)
        self.radius = float(radius)
        self._build(x, values, k, power, "meet the sphere")

    def __call__(self, origins, directions, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate rays.

        Parameters
        ----------
        origins, directions : (q, 3) float
        workers : int
            Threads of the k-d tree query (-1: all cores).

        Returns
        -------
        values : (q, C) float64
            NaN for rays whose line misses the sphere.
        inside : (q,) bool
            The ray meets the sphere.
        """
        return self._answer(two_sphere_coordinates(origins, directions, self.center, self.radius),
                            workers)


class TwoPlaneNearest(_NearestRays):
    """The classic two-plane light field: the ``k`` nearest sample rays, inverse-distance weighted.

    A ray is its points ``(u, v)`` on the camera plane and ``(s, t)`` on the
    focal plane (:func:`two_plane_coordinates`, planes ``z = const``); a query
    ray's value is ``sum_i w_i v_i / sum_i w_i`` over its ``k`` nearest samples
    in R^4, ``w_i = 1 / dist_i**power`` (a sample at distance 0 gives its own
    value). The baseline of forward-facing captures
    (``flatserve lightfield capture-figure``: ``k`` and the focal plane chosen
    in its favour).

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays (at least ``k`` must cross the planes).
    values : (n, C) float, or (n,)
    planes : (float, float)
        z of the camera plane and of the focal plane.
    k : int
    power : float

    Attributes
    ----------
    build_seconds : float
        Time of the k-d tree.
    nsamples : int
        Samples that cross the planes.
    """

    def __init__(self, origins, directions, values, planes=TWO_PLANE_Z[::-1], k: int = 4,
                 power: float = IDW_POWER):
        x = two_plane_coordinates(origins, directions, planes)
        self.planes = tuple(float(z) for z in planes)
        self._build(x, values, k, power, "cross the planes")

    def __call__(self, origins, directions, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate rays: values (q, C), NaN for rays parallel to the planes, and
        ``inside`` (q,) bool (the ray crosses them)."""
        return self._answer(two_plane_coordinates(origins, directions, self.planes), workers)
