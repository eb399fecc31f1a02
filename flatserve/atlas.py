"""Atlases: several charts that together cover every orientation of k-flats.

One tangent-simplex basis (paper Sec. 5.1, Eq. 13-15) charts only the flats
whose direction space is within 45 degrees of its centre's (largest principal
angle; measured, and for lines derived in :mod:`flatserve.basis`: the smallest
eigenvector of ``Q*`` turns by ``phi`` with ``tan(2 phi) = 2 t``).  The paper
says why one chart cannot do (Sec. 1: Grassmannians cannot be covered by one
chart) and leaves the choice of bases open (Sec. 6).  An :class:`Atlas` is a
set of such charts, each with a *domain* given by an angle to its centre:

``inner`` (default 20 deg)
    the chart's blending weight is 1 up to here;
``trusted`` (default 40 deg)
    the blending weight falls smoothly to 0 here (the chart answers queries
    only below it);
``reach`` (default 44 deg)
    samples are inserted into every chart whose centre is closer than this,
    so that a chart's triangulation covers its whole blending domain with
    real samples; below the 45 deg limit (:data:`CHART_LIMIT_DEG`) where the
    coordinates stop round-tripping.

Coverage is a question of orientation only (offsets do not matter: the chart
is equivariant under translations), so a *covering* atlas
(:meth:`Atlas.covering`) chooses centre directions such that every
k-subspace is closer than ``trusted`` to some centre; a *data-driven* atlas
(:meth:`Atlas.for_samples`) places charts where given samples are.

:class:`AtlasField` holds one :class:`~flatserve.field.Field` per chart and
blends their answers with a partition of unity that varies smoothly with the
query flat, so the interpolant has no seam where one chart hands over.

Angles
------
The principal angles between the direction spaces ``span(A_C)`` and
``span(A_F)`` (orthonormal ``A``, (d, k)) are the arccosines of the singular
values of ``A_C^T A_F``; the largest one is ``arccos(sigma_min)``.  The
non-zero principal angles of two k-subspaces equal those of their orthogonal
complements, so the smaller of ``A`` (k columns) and ``N`` (d-k columns) is
used.  Oriented lines (rays, k = 1) use the angle between the unit directions
(``arccos(a_C . a_F)``, in [0, 180] degrees): a centre and its negative are
different charts.

Example
-------
>>> import numpy as np, flatserve
>>> from flatserve.atlas import Atlas, AtlasField
>>> atlas = Atlas.covering(1, 3)                 # 16 icosahedral axes
>>> field = AtlasField(atlas, channels=1)
>>> rng = np.random.default_rng(0)
>>> o, v = rng.normal(size=(3000, 3)), rng.normal(size=(3000, 3))
>>> res = field.add(flatserve.Flats.from_rays(o, v), o[:, 0] ** 2)
>>> res.accepted
3000
"""
from __future__ import annotations

import functools
import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from . import flats as _flats
from ._validate import as_array
from .basis import Basis, select_scale
from .coordinates import NOT_REPRESENTABLE, OK, ROUNDTRIP_TOL
from .embedding import row_product
from .errors import InvalidInputError, SnapshotError
from .options import Order, Outside, choice
from .field import AddResult, Field, PreparedBatch, QueryResult
from .flats import Flats
from .triangulation import RWLock
from .warp import LineWarp

__all__ = [
    "CHART_LIMIT_DEG",
    "INNER_DEG",
    "TRUSTED_DEG",
    "REACH_DEG",
    "COVER_TRAIN_DEG",
    "COVER_RADII_3D",
    "DEFAULT_UNIT",
    "object_unit",
    "GEODESIC_AXES",
    "DEFAULT_SCALE",
    "ICOSAHEDRON_AXES",
    "Atlas",
    "AtlasField",
    "AtlasPrepared",
    "AtlasQueryResult",
    "Routing",
    "bump",
    "haar_frames",
    "max_principal_angle",
    "orientation_frames",
]

#: A tangent-simplex chart (Sec. 5.1) round-trips every flat whose largest
#: principal angle to its centre is below 45 degrees and none beyond.
CHART_LIMIT_DEG = 45.0
#: Blending weight 1 up to this angle to a chart's centre.
INNER_DEG = 20.0
#: Blending weight 0 from this angle on: a chart answers queries only below it.
#: Measured accuracy falls steeply toward the 45 degree limit (DESIGN.md:
#: median error 0.018 at 35-40 degrees, 0.063 at 40-45), so queries are kept
#: inside 40.
TRUSTED_DEG = 40.0
#: Samples are inserted into every chart whose centre is closer than this
#: (at least ``trusted``: a chart must hold the samples around every query it
#: answers; below the 45 degree limit).
REACH_DEG = 44.0
#: A covering atlas for general (k, d) adds centres until every subspace of a
#: training sample is within this angle of one; the radius measured on a fresh
#: sample is then checked to be below ``trusted``.
COVER_TRAIN_DEG = 35.0
#: Scale of the charts of a covering atlas.  The scale does not change the
#: chart: the weights are ``1/m + u / scale`` with ``u`` fixed per flat, so the
#: embedded points are scaled uniformly about the barycentre and their
#: Delaunay triangulation, hence the interpolant, is the same.  It changes the
#: rounding: measured on Haar-random flats with offsets uniform in
#: [-10^3, 10^3]^d, the largest round-trip residual within ``reach`` of a
#: centre is 2.3e-7 (lines in R^3) to 8.2e-7 (planes in R^5) at the paper's
#: 0.01 and 7e-9 to 3.9e-7 at 1; at offsets 10^4, 0.01 fails 16-28 % of the
#: flats against the absolute ``ROUNDTRIP_TOL`` and 1 fails 0-0.5 %.
DEFAULT_SCALE = 1.0
#: The unit of length of a chart (:class:`Atlas` ``unit``): the shift of a
#: line that its chart weighs as much as a turn of one radian.  1: lengths in
#: the flats' own units (the paper's tangent simplex).
DEFAULT_UNIT = 1.0
#: Radii (``inner``, ``trusted``, ``reach``, degrees) of the covering atlases of
#: lines and planes in R^3 (:data:`GEODESIC_AXES`, covering radius 22.69
#: degrees): ``trusted`` 1.3 degrees beyond the covering radius, ``reach`` 3
#: beyond ``trusted``, blending weight 1 up to half of ``trusted``.  The paper's
#: chart stretches a tilt by at most ``1/cos^2(2 trusted)`` = 2.2 there (against
#: 14.5 at the 6 icosahedral axes' 37.4 degrees; the isometric charts of lines,
#: :mod:`flatserve.warp`, undo it); duplication (Haar-random lines) 1.75.
COVER_RADII_3D = (12.0, 24.0, 27.0)
#: Largest extra angle a covering must keep below ``trusted`` (degrees): the
#: margin the checks of :meth:`Atlas.covering` require.
COVER_MARGIN_DEG = 1.0
#: Training sample of the greedy cover, and the fresh sample that measures it.
COVER_TRAIN_N = 20_000
COVER_CHECK_N = 200_000

_GOLDEN = (1.0 + 5.0 ** 0.5) / 2.0
_ico = np.array([[0.0, 1.0, _GOLDEN], [0.0, 1.0, -_GOLDEN], [1.0, _GOLDEN, 0.0],
                 [1.0, -_GOLDEN, 0.0], [_GOLDEN, 0.0, 1.0], [-_GOLDEN, 0.0, 1.0]])
#: The 6 axes through opposite vertices of a regular icosahedron (unit rows).
#: Every direction is within 37.38 degrees of one of them (the angle from a
#: vertex to the centre of an adjacent face); neighbouring axes are 63.43
#: degrees apart.
ICOSAHEDRON_AXES = _ico / np.linalg.norm(_ico, axis=1, keepdims=True)
ICOSAHEDRON_AXES.setflags(write=False)


def _geodesic_axes() -> np.ndarray:
    V = np.concatenate([ICOSAHEDRON_AXES, -ICOSAHEDRON_AXES])  # the 12 vertices
    near = V @ V.T > 0.4  # neighbours: 63.43 degrees apart (cos 0.447)
    faces = [(a, b, c) for a in range(12) for b in range(a + 1, 12) for c in range(b + 1, 12)
             if near[a, b] and near[a, c] and near[b, c]]
    F = np.array([V[list(f)].sum(axis=0) for f in faces])  # 20 face centres
    F = F / np.linalg.norm(F, axis=1, keepdims=True)
    F = F[(F @ np.array([1.0, 2.0, 3.0])) > 0]  # one of each opposite pair: 10 axes
    return np.concatenate([ICOSAHEDRON_AXES, F])


#: 16 axes: the icosahedron's 6 vertex axes and its 10 face axes (the 32
#: vertices of the pentakis dodecahedron, as oriented directions).  Every
#: direction is within 22.69 degrees of one of them (measured on 200,000
#: directions; :meth:`Atlas.covering` stores its measurement); neighbouring
#: axes are 37.38 degrees apart.
GEODESIC_AXES = _geodesic_axes()
GEODESIC_AXES.setflags(write=False)


# ------------------------------------------------------------------------ geometry


def bump(angle, inner: float, trusted: float) -> np.ndarray:
    """Blending weight of a chart at ``angle`` (radians) from its centre.

    ``1`` up to ``inner``, ``0`` from ``trusted`` on, in between
    ``1 - S(t)`` with ``t = (angle - inner) / (trusted - inner)`` and
    ``S(t) = t^3 (6 t^2 - 15 t + 10)`` (twice continuously differentiable).

    Parameters
    ----------
    angle : ndarray, shape (n,)
    inner, trusted : float
        Radians, ``0 <= inner < trusted``.

    Returns
    -------
    ndarray, shape (n,)
    """
    t = np.clip((np.asarray(angle, dtype=np.float64) - inner) / (trusted - inner), 0.0, 1.0)
    return 1.0 - t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _use_normals(k: int, d: int) -> bool:
    """Compare normal spaces (d-k columns) instead of direction spaces (k columns)."""
    return d - k < k


def orientation_frames(flats: Flats, *, normals: bool | None = None) -> np.ndarray:
    """Orthonormal frames of the flats' direction (or normal) spaces.

    Parameters
    ----------
    flats : Flats
        ``n`` k-flats in R^d.
    normals : bool, optional
        Return normal frames (d-k columns) instead of spanning frames (k
        columns); default: whichever has fewer columns (the principal angles
        agree).

    Returns
    -------
    ndarray, shape (n, d, j)
        ``j = k`` (spans) or ``d - k`` (normals).  For rays the unit
        directions, sign kept (the orientation of oriented atlases).
    """
    k, d = flats.k, flats.d
    if normals is None:
        normals = _use_normals(k, d)
    if not normals:
        if k == 0:
            return np.zeros((flats.n, d, 0))
        if flats.form == "rays":
            v = flats.arrays["directions"]
            return (v / np.sqrt(np.einsum("ni,ni->n", v, v))[:, None])[:, :, None]
        if flats.form == "parametric":
            return np.linalg.qr(flats.arrays["A"])[0]
    A, N = _flats.frames(flats.quadrics()[0], k)
    return N if normals else A


def haar_frames(n: int, d: int, j: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` Haar-random j-subspaces of R^d as orthonormal frames (n, d, j).

    The span of a Gaussian (d, j) matrix is Haar-distributed on the
    Grassmannian; its QR factor is an orthonormal frame of it.
    """
    if j == 0:
        return np.zeros((n, d, 0))
    return np.linalg.qr(rng.standard_normal((n, d, j)))[0]


def _cos2_max(C: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``cos^2`` of the largest principal angle between one frame and many.

    ``C`` (d, j), ``F`` (n, d, j): the smallest eigenvalue of ``M^T M`` with
    ``M = C^T F`` (the squared smallest singular value), closed form for
    ``j <= 2``.  Returns (n,) in [0, 1].
    """
    j = C.shape[1]
    if j == 0:
        return np.ones(F.shape[0])
    if j == 1:
        c = row_product(F[:, :, 0], C[:, :1])[:, 0]  # batch-independent bits (route)
        return np.minimum(c * c, 1.0)
    M = np.einsum("di,ndj->nij", C, F)
    if j == 2:
        g11 = M[:, 0, 0] ** 2 + M[:, 1, 0] ** 2
        g22 = M[:, 0, 1] ** 2 + M[:, 1, 1] ** 2
        g12 = M[:, 0, 0] * M[:, 0, 1] + M[:, 1, 0] * M[:, 1, 1]
        h = 0.5 * (g11 - g22)
        lam = 0.5 * (g11 + g22) - np.sqrt(h * h + g12 * g12)
    else:
        lam = np.linalg.eigvalsh(np.swapaxes(M, 1, 2) @ M)[:, 0]
    return np.clip(lam, 0.0, 1.0)


def max_principal_angle(C, F, *, oriented: bool = False) -> np.ndarray:
    """Largest principal angle between centre frames and flat frames, radians.

    Parameters
    ----------
    C : array_like, shape (c, d, j)
        Orthonormal frames of the centres (e.g. ``A`` of :func:`flatserve.flats.frames`).
    F : array_like, shape (n, d, j)
        Orthonormal frames of the flats (:func:`orientation_frames`).
    oriented : bool
        ``j = 1`` only: the angle between the signed directions (0 to pi)
        instead of between the lines (0 to pi/2).

    Returns
    -------
    ndarray, shape (n, c)
        ``arccos(sigma_min(C_c^T F_n))``.
    """
    C = np.asarray(C, dtype=np.float64)
    F = np.asarray(F, dtype=np.float64)
    if oriented:
        return np.arccos(np.clip(F[:, :, 0] @ C[:, :, 0].T, -1.0, 1.0))
    out = np.empty((F.shape[0], C.shape[0]))
    for c in range(C.shape[0]):  # a loop over charts, not flats
        out[:, c] = np.arccos(np.sqrt(_cos2_max(C[c], F)))
    return out


def _complement(C: np.ndarray) -> np.ndarray:
    """Orthonormal frame (d, d-j) of the orthogonal complement of span(C) (d, j)."""
    d, j = C.shape
    _, V = np.linalg.eigh(C @ C.T)
    return V[:, : d - j]


def _greedy_cover(T: np.ndarray, radius: float, first: np.ndarray) -> list[np.ndarray]:
    """Farthest-point centres among frames ``T`` (n, d, j), starting at ``first``.

    Adds the frame farthest (largest principal angle) from every centre so
    far until all of ``T`` is closer than ``radius`` (radians) to a centre.
    """
    centres = [first]
    best = _cos2_max(first, T)
    cos2r = math.cos(radius) ** 2
    while best.min() < cos2r:
        i = int(np.argmin(best))
        centres.append(T[i])
        np.maximum(best, _cos2_max(T[i], T), out=best)
    return centres


@functools.lru_cache(maxsize=32)
def _cover_frames(k: int, d: int, train_deg: float, seed: int, n_train: int) -> np.ndarray:
    """Centre frames (c, d, j) of a covering atlas of k-subspaces of R^d (cached)."""
    j = d - k if _use_normals(k, d) else k
    if j == 0:
        return np.zeros((1, d, 0))
    if (k, d) in ((1, 3), (2, 3)):
        return GEODESIC_AXES[:, :, None].copy()
    rng = np.random.default_rng(seed)
    T = haar_frames(n_train, d, j, rng)
    first = np.eye(d)[:, d - j:]
    return np.stack(_greedy_cover(T, math.radians(train_deg), first))


#: Covering radii measured by :meth:`Atlas.covering`, by (k, d, oriented, train_deg,
#: seed, n_train, check_n): the centres and the measurement are seeded, so a field
#: created again does not measure again (lines in R^3: 0.05 s; 3-flats in R^5,
#: 329 charts: about 17 s).
_COVER_RADIUS: dict[tuple, float] = {}


def _in_units(deg, name):
    if not (isinstance(deg, (int, float, np.floating, np.integer)) and math.isfinite(deg)):
        raise InvalidInputError(f"{name}: expected an angle in degrees, got {deg!r}", name)
    return float(deg)


# ---------------------------------------------------------------------------- atlas


class Routing(NamedTuple):
    """Which charts hold which flats (:meth:`Atlas.route`).

    Attributes
    ----------
    rows : list of ndarray (int64)
        Per chart, the flats (row indices, increasing) whose angle to the
        chart's centre is below the routing radius.
    angles : list of ndarray (float64)
        Per chart, those flats' angles to the centre (radians).
    nearest : ndarray, shape (n,), int64, or None
        The chart whose centre is closest to each flat (None when routed
        with ``nearest=False``).
    nearest_angle : ndarray, shape (n,), or None
        That angle (radians).
    """

    rows: list
    angles: list
    nearest: np.ndarray
    nearest_angle: np.ndarray


class Atlas:
    """Charts (tangent-simplex bases, Sec. 5.1) with angular domains.

    Build with :meth:`covering` (every orientation), :meth:`for_samples`
    (where given samples are) or :meth:`from_centers` (explicit centres,
    checked to cover what they claim).

    Parameters
    ----------
    k, d : int
        k-flats in R^d.
    center_A : array_like, shape (c, d, k)
        Orthonormal spanning frames of the centre flats (for oriented
        atlases the signed centre directions, (c, d, 1)).
    center_N : array_like, shape (c, d, d-k)
        Orthonormal normal frames, orthogonal to ``center_A``.
    center_r : array_like, shape (c, d)
        The centres' closest points to the origin (``Q r = r``, Eq. 3).
    scales : array_like, shape (c,)
        Tangent-simplex scale per chart.
    oriented : bool
        Rays keep their direction (k = 1 only).
    inner, trusted, reach : float
        Degrees, ``0 <= inner < trusted <= reach < 45`` (module docstring).
    unit : float
        The unit of length of the charts (positive, in the flats' units): the
        shift of a flat that a chart weighs as much as a turn of one radian.
        At a chart's centre the tangent simplex moves its flats by ``scale``
        radians of turn and ``scale * unit`` of shift, so a chart of unit
        ``u`` gives a flat the coordinates the unit-1 chart gives the flat
        scaled by ``1/u`` about the origin.  Samples whose values change
        along a shift about as fast as along a turn of ``1/u`` radians are
        interpolated best: for rays of an object, ``u`` about its half-size
        (rays that meet on its surface at depth ``z`` from its centre differ
        by a shift of ``z`` times their turn).  Default
        :data:`DEFAULT_UNIT` (the paper's chart).
    isometric : bool, optional
        Warp each chart's points so that it measures turns and shifts
        everywhere as at its centre (:mod:`flatserve.warp`; lines in R^3
        only).  Default: True for lines in R^3, False otherwise (and for
        atlases stored before there was a choice: :meth:`from_dict`).

    Attributes
    ----------
    bases : list of Basis
        One tangent simplex per chart (``m = (k+1)(d-k)+1`` flats each).
    frames : ndarray, shape (c, d, j)
        What angles are measured against (``center_A`` or ``center_N``).
    info : dict
        How the atlas was built (method, covering radius measured, ...).
    """

    def __init__(self, k: int, d: int, center_A, center_N, center_r, scales, *,
                 oriented: bool = False, inner: float = INNER_DEG,
                 trusted: float = TRUSTED_DEG, reach: float = REACH_DEG,
                 unit: float = DEFAULT_UNIT, isometric: bool | None = None):
        d = int(d)
        k = _flats.check_k(k, d)
        if oriented and k != 1:
            raise InvalidInputError(f"oriented: only lines (k = 1) have an orientation, got "
                                    f"k = {k}", "oriented")
        inner = _in_units(inner, "inner")
        trusted = _in_units(trusted, "trusted")
        reach = _in_units(reach, "reach")
        if not (isinstance(unit, (int, float, np.floating, np.integer))
                and not isinstance(unit, bool) and math.isfinite(unit) and unit > 0):
            raise InvalidInputError(f"unit: expected a positive length, got {unit!r}", "unit")
        unit = float(unit)
        if not 0 <= inner < trusted <= reach < CHART_LIMIT_DEG:
            # named after the radius that breaks the order (reach: too small or too large)
            bad = "reach" if (0 <= inner < trusted and not trusted <= reach < CHART_LIMIT_DEG) \
                else "trusted"
            raise InvalidInputError(
                f"{bad}: need 0 <= inner < trusted <= reach < {CHART_LIMIT_DEG:g} degrees, got "
                f"inner={inner:g}, trusted={trusted:g}, reach={reach:g}", bad)
        r = np.ascontiguousarray(np.asarray(center_r, dtype=np.float64).reshape(-1, d))
        c = r.shape[0]  # (not from center_A: points, k = 0, have empty frames)
        A = np.ascontiguousarray(np.asarray(center_A, dtype=np.float64).reshape(c, d, k))
        N = np.ascontiguousarray(np.asarray(center_N, dtype=np.float64).reshape(c, d, d - k))
        s = np.asarray(scales, dtype=np.float64).reshape(-1)
        if c < 1 or s.shape != (c,):
            raise InvalidInputError(f"scales: expected one scale per centre ({c}), got "
                                    f"{s.shape}", "scales")
        self.k, self.d, self.oriented = k, d, bool(oriented)
        self.inner, self.trusted, self.reach, self.unit = inner, trusted, reach, unit
        self.center_A, self.center_N, self.center_r, self.scales = A, N, r, s
        self.frames = N if _use_normals(k, d) else A
        if isometric is None:
            isometric = (k, d) == (1, 3)
        if not isinstance(isometric, (bool, np.bool_)) or (isometric and (k, d) != (1, 3)):
            raise InvalidInputError(f"isometric: only charts of lines in R^3 can be made isometric, "
                                    f"got {isometric!r} for {k}-flats in R^{d}", "isometric")
        self.isometric = bool(isometric)
        self._warps: list | None = None  # calibrated on first use (warps)
        self.bases = []
        for i in range(c):
            Q = N[i] @ N[i].T
            try:
                B = _unit_simplex(Q, r[i], k, float(s[i]), (A[i], N[i]), unit)
            except InvalidInputError as exc:
                raise InvalidInputError(f"centers: chart {i}: {exc}", "centers") from None
            self.bases.append(B)
        self.info: dict = {}

    # ----------------------------------------------------------------- builders
    @classmethod
    def covering(cls, k: int, d: int, *, oriented: bool = False, scale: float = DEFAULT_SCALE,
                 inner: float | None = None, trusted: float | None = None,
                 reach: float | None = None, train_deg: float = COVER_TRAIN_DEG,
                 seed: int = 0, check_n: int = COVER_CHECK_N,
                 n_train: int = COVER_TRAIN_N, unit: float = DEFAULT_UNIT,
                 isometric: bool | None = None) -> "Atlas":
        """An atlas whose charts hold every k-flat of R^d, centres through the origin.

        Centres.  A chart is accurate near its centre only: its embedding
        stretches a flat's tilt by ``1/cos^2(2 theta)`` at ``theta`` from the
        centre (4x at 30 degrees, 14.5x at 37.4), so its Delaunay cells join
        ever more distant flats (for lines in R^3 the isometric charts,
        :mod:`flatserve.warp`, undo the stretch; the covering was chosen
        before them, and measured again with them: 24 of 24 bunny views beat
        the baseline); and every sample is stored in each chart
        closer than ``reach`` (memory).  The centres are therefore as many
        as keep the charts narrow while the duplication (charts per sample)
        stays below 2: a covering of radius ``rho`` with ``c`` centres
        stores ``c * vol(reach) / vol(sphere)`` samples per sample, at least
        the covering's density (about 1.2-1.4 for good coverings) times
        ``vol(rho + margins) / vol(rho)``, which grows as ``rho`` shrinks.
        For lines and planes in R^3 (directions on the sphere) the 16 axes of
        :data:`GEODESIC_AXES` (icosahedron vertices and face centres;
        covering radius 22.69 degrees, radii :data:`COVER_RADII_3D`,
        duplication 1.75 for Haar-random lines; the 6 icosahedral axes'
        37.4 degrees stretch 14.5x, 42 subdivided-icosahedron directions
        need 2.0).  Otherwise (the space of k-subspaces grows as
        ``k (d - k)`` dimensions, so narrow charts would need hundreds to
        thousands of centres): a greedy farthest-point cover of ``n_train``
        Haar-random subspaces (seeded), started at the span of the last
        axes, until every one is within ``train_deg`` of a centre, with the
        radii :data:`INNER_DEG`, :data:`TRUSTED_DEG`, :data:`REACH_DEG`.  The covering radius is then
        measured on ``check_n`` fresh Haar-random subspaces and must be below
        ``trusted - COVER_MARGIN_DEG`` (stored in :attr:`info`).  Oriented
        atlases (rays) add every centre's negative.

        Parameters
        ----------
        k, d : int
        oriented : bool
        scale : float
            Tangent-simplex scale of every chart (:data:`DEFAULT_SCALE`).
        inner, trusted, reach : float, optional
            Degrees (module docstring); default :data:`COVER_RADII_3D` for
            d = 3, else :data:`INNER_DEG`, :data:`TRUSTED_DEG`,
            :data:`REACH_DEG`.
        train_deg : float
            Radius of the greedy cover on the training sample.
        seed : int
        check_n, n_train : int
        unit : float
            The charts' unit of length (:class:`Atlas`).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).

        Returns
        -------
        Atlas

        Raises
        ------
        InvalidInputError
            ``"trusted"`` when the measured covering radius is not below
            ``trusted - COVER_MARGIN_DEG`` (lower ``train_deg``).
        """
        d = int(d)
        k = _flats.check_k(k, d)
        radii = COVER_RADII_3D if d == 3 else (INNER_DEG, TRUSTED_DEG, REACH_DEG)
        inner, trusted, reach = (radii[i] if v is None else v
                                 for i, v in enumerate((inner, trusted, reach)))
        C = _cover_frames(k, d, float(train_deg), int(seed), int(n_train))
        normals = _use_normals(k, d)
        comp = np.stack([_complement(f) for f in C]) if k and C.shape[2] else None
        if k == 0:
            A, N = np.zeros((1, d, 0)), np.eye(d)[None]
        elif normals:
            A, N = comp, C
        else:
            A, N = C, comp
        if oriented:
            A, N = np.concatenate([A, -A]), np.concatenate([N, N])
        atlas = cls(k, d, A, N, np.zeros((A.shape[0], d)), np.full(A.shape[0], float(scale)),
                    oriented=oriented, inner=inner, trusted=trusted, reach=reach, unit=unit,
                    isometric=isometric)
        key = (k, d, bool(oriented), float(train_deg), int(seed), int(n_train), int(check_n))
        radius = _COVER_RADIUS.get(key)  # the same centres, the same seeded measurement
        if radius is None:
            radius = _COVER_RADIUS[key] = atlas.covering_radius(check_n, seed=seed + 1)
        atlas.info = {"method": "covering", "centres": int(A.shape[0]),
                      "covering_radius_deg": radius, "train_deg": float(train_deg),
                      "check_n": int(check_n), "seed": int(seed)}
        if not radius < atlas.trusted - COVER_MARGIN_DEG:
            raise InvalidInputError(
                f"trusted: {A.shape[0]} centres leave {k}-subspaces of R^{d} {radius:.2f} "
                f"degrees from every centre, not below trusted - margin = "
                f"{atlas.trusted - COVER_MARGIN_DEG:g}", "trusted")
        return atlas

    @classmethod
    def from_centers(cls, centers: Flats, scales=DEFAULT_SCALE, *, oriented: bool = False,
                     inner: float = INNER_DEG, trusted: float = TRUSTED_DEG,
                     reach: float = REACH_DEG, require_cover: bool = True,
                     check_n: int = COVER_CHECK_N, seed: int = 0,
                     unit: float = DEFAULT_UNIT, isometric: bool | None = None) -> "Atlas":
        """An atlas with the given centre flats, checked to cover every orientation.

        Parameters
        ----------
        centers : Flats
            ``c`` k-flats (rays for oriented atlases: their directions are the
            chart orientations).
        scales : float or array_like, shape (c,)
        require_cover : bool
            Measure the covering radius on ``check_n`` Haar-random subspaces
            (oriented: directions) and refuse centres that leave some farther
            than ``trusted`` from every centre.
        unit : float
            The charts' unit of length (:class:`Atlas`).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).

        Raises
        ------
        InvalidInputError
            ``"centers"`` naming the uncovered direction and its angle, or a
            chart whose basis is singular; ``"scales"`` for non-positive
            scales.
        """
        if not isinstance(centers, Flats):
            raise InvalidInputError("centers: expected a flatserve.Flats batch", "centers")
        if oriented and centers.form != "rays":
            raise InvalidInputError(f"centers: an oriented atlas needs rays as centres, got "
                                    f"the form {centers.form!r}", "centers")
        k, d = centers.k, centers.d
        Q, r = centers.quadrics()
        A, N = _flats.frames(Q, k)
        if oriented:
            A = orientation_frames(centers, normals=False)
        s = np.broadcast_to(np.asarray(scales, dtype=np.float64), (centers.n,))
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise InvalidInputError("scales: expected positive numbers", "scales")
        atlas = cls(k, d, A, N, r, s, oriented=oriented, inner=inner, trusted=trusted,
                    reach=reach, unit=unit, isometric=isometric)
        for i, B in enumerate(atlas.bases):
            rep = B.check()
            if not rep.ok:
                raise InvalidInputError(f"centers: chart {i} (scale {s[i]:g}): "
                                        + "; ".join(rep.failures), "centers")
            bad = atlas.probe(i)
            if bad:
                raise InvalidInputError(f"centers: chart {i} (scale {s[i]:g}) does not chart "
                                        f"its domain: {bad}", "centers")
        atlas.info = {"method": "centers", "centres": int(centers.n)}
        if require_cover:
            radius, worst = atlas.covering_radius(check_n, seed=seed, return_worst=True)
            atlas.info.update(covering_radius_deg=radius, check_n=int(check_n))
            if not radius < atlas.trusted:
                raise InvalidInputError(
                    f"centers: {centers.n} centres do not cover every orientation: the "
                    f"direction space spanned by {np.round(worst, 4).tolist()} is "
                    f"{radius:.2f} degrees from every centre (trusted {atlas.trusted:g})",
                    "centers")
        return atlas

    @classmethod
    def for_samples(cls, flats: Flats, *, oriented: bool = False, radius: float = 30.0,
                    fraction: float = 0.99, inner: float = INNER_DEG,
                    trusted: float = TRUSTED_DEG, reach: float = REACH_DEG,
                    max_scale_samples: int = 5000, max_cluster_samples: int = 20_000,
                    seed: int = 0, refine: int = 3, unit: float = DEFAULT_UNIT,
                    isometric: bool | None = None) -> "Atlas":
        """A data-driven atlas: charts where the samples' orientations are.

        1. Greedy cover of the samples' direction spaces (largest principal
           angle; oriented: signed directions): the first centre is the
           extrinsic mean (top eigenvectors of the mean projector
           ``mean A A^T``), then the sample farthest from every centre, until
           every sample is within ``radius`` of one.
        2. ``refine`` rounds: each centre moves to the extrinsic mean of the
           samples nearest to it, kept only while every sample stays within
           ``radius``; then a centre is dropped (smallest clusters first)
           whenever the others, refined without it, still hold every sample
           within ``radius``.
        3. Each centre flat passes through the point nearest to its samples
           in the least-squares sense, ``(sum Q_i)^+ sum r_i`` (the extremum of
           ``q*``, Sec. 2.3); its scale is the paper's bisection
           (:func:`flatserve.basis.select_scale`, ``fraction`` of up to
           ``max_scale_samples`` of its samples inside the simplex).

        Parameters
        ----------
        flats : Flats
            The samples (rays for oriented atlases).
        oriented : bool
        radius : float
            Degrees, ``<= trusted``: the clustering radius.
        fraction : float
            Of :func:`~flatserve.basis.select_scale`.
        max_scale_samples, max_cluster_samples : int
            Steps 1-2 run on a seeded subsample of at most
            ``max_cluster_samples``; then the greedy cover continues on all
            samples until each is within ``radius``.  The bisection uses at
            most ``max_scale_samples`` per chart.
        seed, refine : int
        unit : float
            The charts' unit of length (:class:`Atlas`; the bisection
            chooses each chart's scale in this unit).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).

        Returns
        -------
        Atlas
            ``info`` has the largest sample angle to its nearest centre and
            the samples per chart.
        """
        if not isinstance(flats, Flats):
            raise InvalidInputError(f"flats: expected a flatserve.Flats batch, got "
                                    f"{type(flats).__name__}", "flats")
        if flats.n < 1:
            raise InvalidInputError("flats: expected at least one sample", "flats")
        radius = _in_units(radius, "radius")
        if not 0 < radius <= trusted:
            raise InvalidInputError(f"radius: expected 0 < radius <= trusted = {trusted:g}, "
                                    f"got {radius:g}", "radius")
        k, d = flats.k, flats.d
        if oriented:
            _require_rays(flats, True)
        rad = math.radians(radius)
        F_all = orientation_frames(flats, normals=False if oriented else None)
        rng = np.random.default_rng(seed)
        F = F_all if flats.n <= max_cluster_samples else F_all[
            np.sort(rng.choice(flats.n, max_cluster_samples, replace=False))]
        j = F.shape[2]
        if oriented:
            def dist(C):
                return np.arccos(np.clip(F[:, :, 0] @ C[:, 0], -1.0, 1.0))

            def mean(rows):
                v = F[rows, :, 0].sum(axis=0)
                nv = np.linalg.norm(v)
                return (v / nv)[:, None] if nv > 0 else F[rows[0]]
        else:
            def dist(C):
                return np.arccos(np.sqrt(_cos2_max(C, F)))

            def mean(rows):
                P = np.einsum("ndj,nej->de", F[rows], F[rows]) / len(rows)
                return np.linalg.eigh(P)[1][:, d - j:]
        if j == 0:
            C = [np.zeros((d, 0))]
        else:
            C = [mean(np.arange(flats.n))]
            best = dist(C[0])
            while best.max() >= rad:
                i = int(np.argmax(best))
                C.append(F[i])
                np.minimum(best, dist(F[i]), out=best)
            C = _refine(C, dist, mean, rad, refine)
            # prune: drop the centres (smallest clusters first) that the others
            # cover without them, then refine again
            pruned = True
            while pruned and len(C) > 1:
                pruned = False
                D = np.stack([dist(c) for c in C], axis=1)
                for i in np.argsort(np.bincount(D.argmin(axis=1), minlength=len(C))):
                    rest = _refine(C[:i] + C[i + 1:], dist, mean, rad, refine, force=True)
                    if np.stack([dist(c) for c in rest], axis=1).min(axis=1).max() < rad:
                        C, pruned = rest, True
                        break
        F = F_all  # every sample within radius: continue the greedy cover on all of them
        if j:
            best = np.stack([dist(c) for c in C], axis=1).min(axis=1)
            while best.max() >= rad:
                i = int(np.argmax(best))
                C.append(F[i])
                np.minimum(best, dist(F[i]), out=best)
        D = np.stack([dist(c) for c in C], axis=1)
        near = D.argmin(axis=1)
        Q, r = flats.quadrics()
        normals = _use_normals(k, d) and not oriented
        As, Ns, rs, ss, counts, cover = [], [], [], [], [], []
        for i, c in enumerate(C):
            rows = np.flatnonzero(near == i)
            if rows.size == 0:
                continue
            if k == 0:
                a, n = np.zeros((d, 0)), np.eye(d)
            elif normals:
                a, n = _complement(c), c
            else:
                a, n = c, _complement(c)
            Qc = n @ n.T
            x = np.linalg.pinv(Q[rows].sum(axis=0)) @ r[rows].sum(axis=0)
            rc = Qc @ x
            sub = rows if rows.size <= max_scale_samples else rng.choice(
                rows, max_scale_samples, replace=False)
            sel = select_scale(Q[sub], r[sub], lambda sc, Qc=Qc, rc=rc, a=a, n=n:
                               _unit_simplex(Qc, rc, k, sc, (a, n), unit),
                               fraction=fraction, lo=1e-3, hi=1e3)
            As.append(a)
            Ns.append(n)
            rs.append(rc)
            ss.append(sel.scale)
            counts.append(int(rows.size))
            cover.append(sel.coverage)
        atlas = cls(k, d, np.stack(As), np.stack(Ns), np.stack(rs), np.array(ss),
                    oriented=oriented, inner=inner, trusted=trusted, reach=reach, unit=unit,
                    isometric=isometric)
        atlas.info = {"method": "samples", "centres": len(As), "radius_deg": radius,
                      "max_sample_angle_deg": float(np.degrees(D.min(axis=1).max())),
                      "samples_per_chart": counts, "convex_coverage": cover}
        return atlas

    # ------------------------------------------------------------------ queries
    def probe(self, chart: int, distance: float | None = None) -> str:
        """Check that a chart round-trips flats at the edge of its domain.

        Probe flats: the centre with each spanning vector ``a_i`` turned by
        ``reach`` toward each normal ``n_j``, moved by ``distance`` along
        ``n_j``; and the centre moved by ``distance`` along each ``n_j``
        (default: the atlas's ``unit``).

        Returns
        -------
        str
            Empty when every probe round-trips, else what failed.
        """
        A, N, r0 = self.center_A[chart], self.center_N[chart], self.center_r[chart]
        k, d = self.k, self.d
        distance = self.unit if distance is None else float(distance)
        t = math.radians(self.reach)
        As, bs = [], []
        for j in range(d - k):
            bs.append(r0 + distance * N[:, j])
            As.append(A.copy())
            for i in range(k):
                Ai = A.copy()
                Ai[:, i] = math.cos(t) * A[:, i] + math.sin(t) * N[:, j]
                As.append(Ai)
                bs.append(r0 + distance * N[:, j])
        if k == 0:
            Q = np.broadcast_to(np.eye(d), (len(bs), d, d))
            f = Flats.from_quadrics(Q, np.array(bs), 0)
        else:
            f = Flats.from_parametric(np.array(As), np.array(bs))
        co = self.bases[chart].coordinates_of(f)
        if (co.status == OK).all():
            return ""
        worst = float(np.nanmax(co.residual))
        return (f"{int((co.status != OK).sum())} of {len(bs)} probe flats ({self.reach:g} "
                f"degrees and {distance:g} from the centre) do not round-trip (largest "
                f"residual {worst:.3g})")

    @property
    def ncharts(self) -> int:
        return len(self.bases)

    def __len__(self) -> int:
        return self.ncharts

    def __repr__(self) -> str:
        return (f"Atlas(k={self.k}, d={self.d}, charts={self.ncharts}, oriented={self.oriented}, "
                f"inner={self.inner:g}, trusted={self.trusted:g}, reach={self.reach:g}, "
                f"unit={self.unit:g})")

    def check_flats(self, flats: Flats) -> Flats:
        """Check that ``flats`` fit the atlas (dimension, orientation).

        Raises
        ------
        InvalidInputError
            Naming the first array of the batch: wrong (k, d), or a form
            without orientation (``parametric``, ``flats``) given to an
            oriented atlas.
        """
        if not isinstance(flats, Flats):
            raise InvalidInputError(
                f"flats: expected a flatserve.Flats batch, got {type(flats).__name__}", "flats")
        if flats.k != self.k or flats.d != self.d:
            arg = next(iter(flats.arrays))
            raise InvalidInputError(f"{arg}: this atlas charts {self.k}-flats in R^{self.d}, "
                                    f"got {flats.k}-flats in R^{flats.d}", arg)
        _require_rays(flats, self.oriented)
        return flats

    def angles(self, flats: Flats) -> np.ndarray:
        """(n, c) angles (radians) of each flat to each chart's centre.

        The largest principal angle between direction spaces; for oriented
        atlases the angle between the ray's direction and the centre's
        (module docstring).
        """
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        return max_principal_angle(self.frames, F, oriented=self.oriented)

    def route(self, flats: Flats, radius: float, *, nearest: bool = True) -> Routing:
        """Per chart, the flats closer than ``radius`` (degrees) to its centre.

        Batched: one matrix product (lines) or one closed-form 2x2 eigenvalue
        per flat and chart, one comparison pass over all of them; ``arccos``
        only for the rows kept.

        Parameters
        ----------
        flats : Flats
        radius : float
            Degrees (``reach`` for samples, ``trusted`` for queries).
        nearest : bool
            Also find each flat's nearest chart (the upload path needs it, a
            query does not): ``Routing.nearest`` and ``nearest_angle`` are
            None when False.

        Returns
        -------
        Routing
        """
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        n, c = flats.n, self.ncharts
        cr = math.cos(math.radians(radius))
        rows, angles = [], []
        if self.oriented or F.shape[2] == 1:
            # (n, c); row by row in a fixed order: a flat's routing (which
            # charts, what weights) must not depend on the rest of its batch
            dots = row_product(F[:, :, 0], self.frames[:, :, 0].T)
            if not self.oriented:
                np.abs(dots, out=dots)
            held = np.ascontiguousarray((dots > cr).T)  # (c, n): one pass, rows contiguous
            for i in range(c):
                sel = np.flatnonzero(held[i])
                rows.append(sel)
                angles.append(np.arccos(np.minimum(dots[sel, i], 1.0)))
            if not nearest:
                return Routing(rows, angles, None, None)
            near = dots.argmax(axis=1)
            best = dots[np.arange(n), near]
            return Routing(rows, angles, near, np.arccos(np.clip(best, -1.0, 1.0)))
        cr2 = cr * cr
        if nearest:
            best = np.full(n, -1.0)
            near = np.zeros(n, dtype=np.int64)
        for i in range(c):
            c2 = _cos2_max(self.frames[i], F)
            sel = np.flatnonzero(c2 > cr2)
            rows.append(sel)
            angles.append(np.arccos(np.sqrt(c2[sel])))
            if nearest:
                better = c2 > best
                best[better] = c2[better]
                near[better] = i
        if not nearest:
            return Routing(rows, angles, None, None)
        return Routing(rows, angles, near, np.arccos(np.sqrt(np.clip(best, 0.0, 1.0))))

    def held(self, flats: Flats, radius: float) -> np.ndarray:
        """Per chart, how many flats are closer than ``radius`` (degrees) to its centre.

        The sizes of :meth:`route`'s ``rows`` (the same test), without the angles:
        one matrix product for lines.  ``held(flats, reach).sum()`` is the number
        of chart vertices a batch adds (before round-trip rejections).

        Returns
        -------
        ndarray, shape (c,), int64
        """
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        cr = math.cos(math.radians(radius))
        if self.oriented or F.shape[2] == 1:
            dots = row_product(F[:, :, 0], self.frames[:, :, 0].T)  # (n, c), as route
            if not self.oriented:
                np.abs(dots, out=dots)
            return np.count_nonzero(dots > cr, axis=0).astype(np.int64)
        return np.array([np.count_nonzero(_cos2_max(C, F) > cr * cr) for C in self.frames],
                        dtype=np.int64)

    def covering_radius(self, n: int = COVER_CHECK_N, *, seed: int = 1,
                        return_worst: bool = False, batch: int = 50_000):
        """Largest angle (degrees) of ``n`` Haar-random orientations to the nearest centre.

        Oriented atlases sample directions uniformly on the sphere.

        Returns
        -------
        float, or (float, ndarray (d, j)) with the worst orientation's frame
        """
        rng = np.random.default_rng(seed)
        j = self.frames.shape[2]
        worst_c, worst_f = 2.0, None
        for start in range(0, n, batch):
            m = min(batch, n - start)
            if self.oriented:
                v = rng.standard_normal((m, self.d))
                F = (v / np.linalg.norm(v, axis=1, keepdims=True))[:, :, None]
                best = (F[:, :, 0] @ self.frames[:, :, 0].T).max(axis=1)
            else:
                F = haar_frames(m, self.d, j, rng)
                best = np.max([np.sqrt(_cos2_max(C, F)) for C in self.frames], axis=0)
            i = int(np.argmin(best))
            if best[i] < worst_c:
                worst_c, worst_f = float(best[i]), F[i]
        deg = float(np.degrees(np.arccos(np.clip(worst_c, -1.0, 1.0))))
        return (deg, worst_f) if return_worst else deg

    # ------------------------------------------------------------- persistence
    @property
    def warps(self) -> list:
        """Per chart its :class:`~flatserve.warp.LineWarp` (isometric atlases), else None.

        Calibrated on first use, or as stored (:meth:`from_dict`: a field
        rebuilt from its log keeps the warps it was built with, whatever
        the calibration of the code that rebuilds it)."""
        if self._warps is None:
            if not self.isometric:
                self._warps = [None] * self.ncharts
            else:
                out = []
                for i, B in enumerate(self.bases):
                    try:
                        out.append(LineWarp.calibrate(B))
                    except InvalidInputError as exc:
                        raise InvalidInputError(f"centers: chart {i} (scale "
                                                f"{self.scales[i]:g}): {exc}", "centers") from None
                self._warps = out
        return self._warps

    @staticmethod
    def spec_isometric(spec: dict) -> bool:
        """Whether the atlas stored as ``spec`` (:meth:`to_dict`) has isometric charts:
        a spec written before there was a choice has the paper's charts."""
        return bool(spec.get("isometric", False))

    def chart_field(self, i: int, channels: int = 1, *,
                    roundtrip_tol: float = ROUNDTRIP_TOL) -> Field:
        """An empty single-chart :class:`~flatserve.field.Field` of chart ``i``
        (its basis, and its warp when the atlas is isometric)."""
        return Field(self.bases[i], channels, roundtrip_tol=roundtrip_tol, warp=self.warps[i])

    def to_dict(self) -> dict:
        """JSON-able description (centres, scales, radii); :meth:`from_dict` inverts it."""
        return {"k": self.k, "d": self.d, "oriented": self.oriented, "inner": self.inner,
                "trusted": self.trusted, "reach": self.reach, "unit": self.unit,
                "isometric": self.isometric,
                **({"warps": [w.to_dict() for w in self.warps]} if self.isometric else {}),
                "center_A": self.center_A.tolist(), "center_N": self.center_N.tolist(),
                "center_r": self.center_r.tolist(), "scales": self.scales.tolist(),
                "info": self.info}

    @classmethod
    def from_dict(cls, spec: dict) -> "Atlas":
        """The atlas described by :meth:`to_dict` (no covering measurement repeated)."""
        atlas = cls(int(spec["k"]), int(spec["d"]), np.array(spec["center_A"]),
                    np.array(spec["center_N"]), np.array(spec["center_r"]),
                    np.array(spec["scales"]), oriented=bool(spec["oriented"]),
                    inner=spec["inner"], trusted=spec["trusted"], reach=spec["reach"],
                    unit=spec.get("unit", DEFAULT_UNIT),
                    isometric=cls.spec_isometric(spec))
        if atlas.isometric and "warps" in spec:
            warps = [LineWarp.from_dict(w) for w in spec["warps"]]
            if len(warps) != atlas.ncharts:
                raise InvalidInputError(f"warps: {len(warps)} for {atlas.ncharts} charts", "warps")
            atlas._warps = warps  # as stored
        atlas.info = dict(spec.get("info", {}))
        return atlas


def object_unit(radius: float) -> float:
    """The unit of length (:class:`Atlas` ``unit``) for rays of an object of this radius.

    ``2 radius / 3``: the mean depth, from the centre, of the surface of a
    ball of that radius as a viewer sees it (``sqrt(R^2 - rho^2)`` averaged
    over the disc ``rho < R`` it covers).  Two rays that meet on the surface
    at depth ``z`` differ by a shift of ``z`` times their turn, so in this
    unit a turn and the shift it makes on a typical visible point count
    alike.  Measured on the 360-degree bunny (docs/orbit-results.md, 100,000
    rays, 24 views, radius 0.5): units 0.7, 0.5 and 1/3 gave ours - baseline
    at least -0.71, -0.22 and +0.05 dB.

    Parameters
    ----------
    radius : float
        Positive: the radius of a ball about the atlas's origin that holds
        the object (something a user knows without rendering).

    Returns
    -------
    float
    """
    if not (isinstance(radius, (int, float, np.floating, np.integer))
            and not isinstance(radius, bool) and math.isfinite(radius) and radius > 0):
        raise InvalidInputError(f"radius: expected a positive length, got {radius!r}", "radius")
    return 2.0 * float(radius) / 3.0


def _unit_simplex(Q, r, k: int, scale: float, frames, unit: float) -> Basis:
    """The tangent simplex around the flat (Q, r) whose shifts are ``unit`` times
    its turns: the unit-1 simplex around (Q, r / unit), scaled by ``unit`` about
    the origin (Atlas ``unit``)."""
    if unit == 1.0:
        return Basis.tangent_simplex(Q, r, k, scale, frames=frames)
    B = Basis.tangent_simplex(Q, np.asarray(r) / unit, k, scale, frames=frames)
    U = Basis(B.Q, B.r * unit, k)
    U.center, U.scale, U.variant = (B.center[0], B.center[1] * unit), B.scale, B.variant
    return U


def _refine(C, dist, mean, rad, rounds, force=False):
    """Move each centre to the mean of its nearest samples while all stay within ``rad``.

    ``force``: take the moves whatever the coverage (to test a pruned set).
    """
    for _ in range(rounds):
        near = np.stack([dist(c) for c in C], axis=1).argmin(axis=1)
        C2 = [mean(np.flatnonzero(near == i)) if (near == i).any() else C[i]
              for i in range(len(C))]
        if not force and not np.stack([dist(c) for c in C2], axis=1).min(axis=1).max() < rad:
            break
        C = C2
    return C


def _require_rays(flats: Flats, oriented: bool) -> None:
    if oriented and flats.form != "rays":
        arg = next(iter(flats.arrays))
        raise InvalidInputError(
            f"{arg}: this atlas is oriented (a ray and its reverse are different samples); "
            f"the form {flats.form!r} ({' + '.join(flats.arrays)}) has no orientation: give "
            "rays (origins + directions)", arg)


# ---------------------------------------------------------------------- atlas field


@dataclass(frozen=True)
class AtlasPrepared:
    """A batch routed and charted by :meth:`AtlasField.prepare`, not yet inserted.

    Attributes
    ----------
    nrows : int
        Rows of the input batch.
    own : list of PreparedBatch or None
        Per chart, the accepted rows whose nearest centre is this chart's.
    shared : list of PreparedBatch or None
        Per chart, the accepted rows that are nearer to another centre (the
        overlap: inserted so that the chart covers its blending domain).
    accepted_rows : ndarray (int64)
        Rows accepted by at least one chart.
    rejected : ndarray (int64)
        Rows no chart accepted.
    reasons : list of str
        One per rejected row.
    """

    nrows: int
    own: list
    shared: list
    accepted_rows: np.ndarray
    rejected: np.ndarray
    reasons: list

    @property
    def accepted(self) -> int:
        return int(self.accepted_rows.size)


@dataclass(frozen=True)
class AtlasQueryResult(QueryResult):
    """:class:`~flatserve.field.QueryResult` of an :class:`AtlasField`.

    ``values`` is the blend ``sum_i w_i v_i`` over the charts whose domain
    holds the query (partition-of-unity weights ``w_i``).  With
    ``return_weights``, ``ids``/``weights`` have shape (q, P, D+1): per
    contributing chart (``charts`` (q, P), -1 for none) the chart's sample
    ids and its barycentric weights times ``w_i``, so that
    ``values[q] = sum_{p, v} weights[q, p, v] * chart_values[charts[q, p]][ids[q, p, v]]``.
    """

    charts: np.ndarray | None = None


def _slices(parts, step: int) -> list[list]:
    """``(field, PreparedBatch, own)`` parts cut into groups of at most ``step``
    samples over all charts, in order (a part larger than ``step`` is cut)."""
    groups, cur, n = [], [], 0
    for f, p, own in parts:
        for lo in range(0, p.accepted, step):
            size = min(step, p.accepted - lo)
            piece = p if size == p.accepted else PreparedBatch(
                size, p.x[lo:lo + step], p.values[lo:lo + step], _NO_ROWS, [])
            if cur and n + size > step:
                groups.append(cur)
                cur, n = [], 0
            cur.append((f, piece, own))
            n += size
    if cur:
        groups.append(cur)
    return groups


class AtlasField:
    """Values sampled on k-flats, over an :class:`Atlas`: one Field per chart, blended.

    Every sample is inserted into each chart whose centre is closer than
    ``atlas.reach``; a query is answered by every chart whose centre is
    closer than ``atlas.trusted``, and the answers are blended with the
    partition of unity ``w_i = bump(angle_i) / sum_j bump(angle_j)``
    (:func:`bump`), which varies continuously (C^2) with the query flat: the
    interpolant has no seam where one chart hands over to the next.  Charts
    whose answer is missing (outside their samples' hull) are left out of the
    sum.  Deep inside a chart (no other centre closer than ``trusted``) the
    answer is that chart's :class:`~flatserve.field.Field`'s.

    Thread safety as :class:`~flatserve.field.Field`: readers together, a
    writer alone.  The field's own readers/writer lock makes a batch atomic
    across charts: :meth:`query` and :meth:`save` see a whole
    :meth:`insert_prepared` batch in every chart, or in none.

    Parameters
    ----------
    atlas : Atlas
    channels : int
    roundtrip_tol : float
        Of every chart's Field.
    """

    def __init__(self, atlas: Atlas, channels: int = 1, *,
                 roundtrip_tol: float = ROUNDTRIP_TOL):
        if not isinstance(atlas, Atlas):
            raise InvalidInputError(f"atlas: expected a flatserve.atlas.Atlas, got "
                                    f"{type(atlas).__name__}", "atlas")
        self.atlas = atlas
        self.fields = [atlas.chart_field(i, channels, roundtrip_tol=roundtrip_tol)
                       for i in range(atlas.ncharts)]
        self.k, self.d, self.ndim = atlas.k, atlas.d, self.fields[0].ndim
        self.channels = self.fields[0].channels
        self.roundtrip_tol = self.fields[0].roundtrip_tol
        self._nsamples = 0
        self._nrejected = 0
        self._lock = RWLock()

    # ------------------------------------------------------------------ sizes
    @property
    def nsamples(self) -> int:
        """Distinct samples (each counted in its nearest chart)."""
        return self._nsamples

    @property
    def nstored(self) -> int:
        """Vertices over all charts (a sample counts once per chart holding it)."""
        return int(sum(f.nsamples for f in self.fields))

    @property
    def duplication(self) -> float:
        """``nstored / nsamples``: how many charts hold a sample on average."""
        return self.nstored / self._nsamples if self._nsamples else float("nan")

    @property
    def nsimplex(self) -> int:
        """Cells over all charts' triangulations."""
        return int(sum(f.nsimplex for f in self.fields))

    @property
    def samples_per_chart(self) -> list[int]:
        return [f.nsamples for f in self.fields]

    @property
    def nrejected(self) -> int:
        return self._nrejected

    # --------------------------------------------------------------- writers
    def _values(self, values, n: int) -> np.ndarray:
        v = np.asarray(values)
        if v.ndim == 1 and self.channels == 1:
            v = v[:, None]
        return as_array(v, "values", (n, self.channels))

    def prepare(self, flats: Flats, values, *, defer: bool = False
                ) -> "AtlasPrepared | Callable[[], AtlasPrepared]":
        """Route a batch to the charts whose domain (``reach``) holds each row, and chart it.

        Reads only the atlas; :meth:`insert_prepared` completes it.

        Parameters
        ----------
        flats : Flats
            ``n`` k-flats in R^d (rays for oriented atlases).
        values : (n, C) float, or (n,) when C == 1
        defer : bool
            Validate now (raising for bad input) but return a zero-argument
            callable that routes and charts when called (as
            :meth:`Field.prepare`): once validated, every row gets a decision.

        Returns
        -------
        AtlasPrepared, or a callable returning one when ``defer``

        Raises
        ------
        InvalidInputError
            Wrong (k, d), orientation-free forms for an oriented atlas
            (naming the form's first array), bad ``values``.
        """
        self.atlas.check_flats(flats)
        values = self._values(values, flats.n)
        if defer:
            return functools.partial(self._prepare, flats, values)
        return self._prepare(flats, values)

    def _prepare(self, flats: Flats, values: np.ndarray) -> AtlasPrepared:
        n = flats.n
        ro = self.atlas.route(flats, self.atlas.reach)
        taken = np.zeros(n, dtype=bool)
        first_reason: dict[int, str] = {}
        own, shared = [], []
        for c, rows in enumerate(ro.rows):
            if rows.size == 0:
                own.append(None)
                shared.append(None)
                continue
            pb = self.fields[c].prepare(flats.take(rows), values[rows])
            okm = np.ones(rows.size, dtype=bool)
            okm[pb.rejected] = False
            for i, why in zip(pb.rejected.tolist(), pb.reasons):
                first_reason.setdefault(int(rows[i]), f"chart {c}: {why}")
            acc = rows[okm]
            taken[acc] = True
            mine = ro.nearest[acc] == c
            own.append(PreparedBatch(int(mine.sum()), pb.x[mine], pb.values[mine],
                                     np.empty(0, np.int64), []))
            shared.append(PreparedBatch(int((~mine).sum()), pb.x[~mine], pb.values[~mine],
                                        np.empty(0, np.int64), []))
        rejected = np.flatnonzero(~taken).astype(np.int64)
        reach = self.atlas.reach
        reasons = [first_reason.get(int(i), (
            f"outside every chart's domain: {math.degrees(ro.nearest_angle[i]):.2f} degrees "
            f"from the nearest centre (chart {int(ro.nearest[i])}), charts reach {reach:g}"))
            for i in rejected.tolist()]
        return AtlasPrepared(n, own, shared, np.flatnonzero(taken).astype(np.int64), rejected,
                             reasons)

    def insert_prepared(self, batch: AtlasPrepared, *,
                        slice_rows: int | None = None) -> AddResult:
        """Insert a :meth:`prepare`-d batch into its charts (a writer).

        Parameters
        ----------
        batch : AtlasPrepared
        slice_rows : int, optional
            As :meth:`Field.insert_prepared`: insert at most this many samples
            (counted over the charts) at a time, so that concurrent queries get in
            between slices. Each slice is atomic: a batch holding at most
            ``slice_rows`` samples over all its charts is seen in every chart or in
            none; a larger one is seen in part (some charts, or part of a chart)
            until its last slice is in. Default: the whole batch at once.
        """
        if not isinstance(batch, AtlasPrepared) or len(batch.own) != len(self.fields):
            raise InvalidInputError("batch: expected an AtlasPrepared made by this field",
                                    "batch")
        if slice_rows is not None and not (isinstance(slice_rows, (int, np.integer))
                                           and slice_rows >= 1):
            raise InvalidInputError(f"slice_rows: expected a positive integer or None, got "
                                    f"{slice_rows!r}", "slice_rows")
        parts = [(f, p, own) for f, o, s in zip(self.fields, batch.own, batch.shared)
                 for p, own in ((o, True), (s, False)) if p is not None and p.accepted]
        if slice_rows is None or not parts:
            groups = [parts]
        else:
            groups = _slices(parts, int(slice_rows))
        duplicates = 0
        for i, group in enumerate(groups):
            with self._lock.write():  # a whole batch, or one slice
                for f, p, own in group:
                    res = f.insert_prepared(p)
                    if own:  # a sample counts once, in its nearest chart
                        duplicates += res.duplicates
                        self._nsamples += res.accepted - res.duplicates
                if i == len(groups) - 1:
                    self._nrejected += int(batch.rejected.size)
        return AddResult(accepted=batch.accepted, rejected=batch.rejected,
                         reasons=batch.reasons, duplicates=duplicates,
                         nsamples=self._nsamples)

    def add(self, flats: Flats, values) -> AddResult:
        """Add samples: ``insert_prepared(prepare(flats, values))`` (a writer).

        Returns
        -------
        AddResult
            ``duplicates`` counts rows that coincided with a sample already in
            their nearest chart; ``nsamples`` the distinct samples afterwards.
        """
        return self.insert_prepared(self.prepare(flats, values))

    # --------------------------------------------------------------- readers
    def query(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
              order: Order | str = Order.HILBERT,
              threads: int | None = None, return_weights: bool = False,
              blocking: bool = True) -> "AtlasQueryResult | None":
        """Interpolate at flats: every chart holding the query, blended.

        Parameters
        ----------
        flats : Flats
            ``q`` k-flats in R^d.
        outside, order, threads
            Passed to each chart's :meth:`Field.query`.
        return_weights : bool
            Also return per contributing chart the sample ids and weights
            (:class:`AtlasQueryResult`).
        blocking : bool
            False: return None at once instead of waiting for an insert in progress.

        Returns
        -------
        AtlasQueryResult
            ``status`` is OK when some chart's coordinates round-trip;
            ``NOT_REPRESENTABLE`` when no chart's domain holds the query.
            ``inside`` when some chart with positive weight answered from
            inside its samples' hull.
        """
        outside, order = choice(outside, Outside, "outside"), choice(order, Order, "order")
        at = self.atlas
        ro = at.route(flats, at.trusted, nearest=False)
        if blocking:
            self._lock.acquire_read()
        elif not self._lock.try_acquire_read():
            return None
        try:  # charts change only under this lock's write side: they never make us wait
            return self._query(flats, ro, outside, order, threads, return_weights)
        finally:
            self._lock.release_read()

    def _query(self, flats, ro, outside, order, threads, return_weights) -> AtlasQueryResult:
        # Per chart holding rows: its Field's answer on those rows only, blended
        # into num / den in chart order (the sums of a row are always added in
        # increasing chart order, from 0.0).
        at = self.atlas
        n, C = flats.n, self.channels
        num = np.zeros((n, C))
        den = np.zeros(n)
        inside = np.zeros(n, dtype=bool)
        status = np.full(n, NOT_REPRESENTABLE, dtype=np.int8)
        inner, trusted = math.radians(at.inner), math.radians(at.trusted)
        if return_weights:
            counts = np.bincount(np.concatenate(ro.rows), minlength=n) if n else np.zeros(0, int)
            P = int(counts.max(initial=0))
            D1 = self.ndim + 1
            ids = np.full((n, P, D1), -1, dtype=np.int64)
            wts = np.zeros((n, P, D1))
            charts = np.full((n, P), -1, dtype=np.int64)
            blend = np.zeros((n, P))
            slot = np.zeros(n, dtype=np.int64)
        for c, rows in enumerate(ro.rows):
            if rows.size == 0 or self.fields[c].nsamples == 0:
                continue
            b = bump(ro.angles[c], inner, trusted)
            res = self.fields[c].query(flats.take(rows), outside=outside, order=order,
                                       threads=threads, return_weights=return_weights)
            v = res.values
            fin = np.isfinite(v)
            good = fin[:, 0] if C == 1 else fin.all(axis=1)
            w = b if good.all() else np.where(good, b, 0.0)  # the common case: no masking
            if C == 1:  # 1-D scatters (much faster than (m, 1) ones)
                num[:, 0][rows] += w * (v[:, 0] if w is b else np.where(good, v[:, 0], 0.0))
            else:
                num[rows] += w[:, None] * (v if w is b else np.where(good[:, None], v, 0.0))
            den[rows] += w
            inside[rows] |= res.inside & (w > 0)
            status[rows[res.status == OK]] = OK
            if return_weights:
                s = slot[rows]
                ids[rows, s] = res.ids
                wts[rows, s] = np.where(good[:, None], res.weights, 0.0)
                charts[rows, s] = c
                blend[rows, s] = w
                slot[rows] += 1
        has = den > 0
        values = np.full((n, C), np.nan)
        np.divide(num, den[:, None], out=values, where=has[:, None])
        if return_weights:
            with np.errstate(invalid="ignore", divide="ignore"):
                wts *= (blend / np.where(has, den, np.nan)[:, None])[:, :, None]
            wts[~has] = np.nan
            return AtlasQueryResult(values, inside, status, ids, wts, charts)
        return AtlasQueryResult(values, inside, status)

    def describe(self) -> dict:
        """JSON-able summary: the atlas's radii and, per chart, centre, scale, samples.

        Returns
        -------
        dict
            ``{"k", "d", "oriented", "inner", "trusted", "reach", "unit", "isometric", "info",
            "nsamples", "nstored", "duplication", "charts": [{"center": {"A",
            "r"}, "scale", "samples"}, ...]}``.
        """
        at = self.atlas
        return {
            "k": at.k, "d": at.d, "oriented": at.oriented, "inner": at.inner,
            "trusted": at.trusted, "reach": at.reach, "unit": at.unit,
            "isometric": at.isometric, "info": at.info,
            "nsamples": self.nsamples, "nstored": self.nstored,
            "duplication": None if not self._nsamples else self.duplication,
            "charts": [{"center": {"A": at.center_A[i].tolist(), "r": at.center_r[i].tolist()},
                        "scale": float(at.scales[i]), "samples": f.nsamples}
                       for i, f in enumerate(self.fields)],
        }

    # ----------------------------------------------------------- persistence
    def save(self, path: str | os.PathLike) -> None:
        """Write the field to one file ``path``.

        Layout: 8-byte magic ``FSATLAS\\0``, uint32 version, uint64 metadata
        length, the metadata JSON (``{"atlas": Atlas.to_dict(), "channels",
        "roundtrip_tol", "nsamples", "nrejected", "charts": c}``), then per
        chart a uint64 length and that chart's field file
        (:meth:`Field.save`, ``flatserve/field.py``).  Written, flushed and
        fsync'd; not atomic by itself (the service writes to a temporary
        file and renames it).  A reader: may run beside queries; a batch
        inserted meanwhile waits (the snapshot holds whole batches).
        """
        meta = json.dumps({"atlas": self.atlas.to_dict(), "channels": self.channels,
                           "roundtrip_tol": self.roundtrip_tol, "nsamples": self._nsamples,
                           "nrejected": self._nrejected,
                           "charts": len(self.fields)}).encode()
        with self._lock.read(), open(path, "wb") as fh:
            fh.write(_ATLAS_HEADER.pack(_ATLAS_MAGIC, _ATLAS_VERSION, len(meta)))
            fh.write(meta)
            for f in self.fields:
                at = fh.tell()
                fh.write(_LENGTH.pack(0))
                size = f.write_to(fh)
                fh.seek(at)
                fh.write(_LENGTH.pack(size))
                fh.seek(0, os.SEEK_END)
            fh.flush()
            os.fsync(fh.fileno())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "AtlasField":
        """Read a field written by :meth:`save`.

        Raises
        ------
        SnapshotError
            The file is truncated, damaged or of another format.
        """
        data = memoryview(Path(path).read_bytes())
        if len(data) < _ATLAS_HEADER.size:
            raise SnapshotError(f"{path}: truncated atlas field file ({len(data)} bytes)")
        magic, version, mlen = _ATLAS_HEADER.unpack_from(data)
        if magic != _ATLAS_MAGIC:
            raise SnapshotError(f"{path}: not a flatserve atlas field file (bad magic)")
        if version != _ATLAS_VERSION:
            raise SnapshotError(f"{path}: atlas field file version {version}, expected "
                                f"{_ATLAS_VERSION}")
        off = _ATLAS_HEADER.size
        if off + mlen > len(data):
            raise SnapshotError(f"{path}: truncated atlas field metadata")
        try:
            meta = json.loads(bytes(data[off:off + mlen]))
            atlas = Atlas.from_dict(meta["atlas"])
            ncharts = int(meta["charts"])
            obj = cls(atlas, int(meta["channels"]), roundtrip_tol=float(meta["roundtrip_tol"]))
            nsamples, nrejected = int(meta["nsamples"]), int(meta["nrejected"])
        except (KeyError, TypeError, ValueError, InvalidInputError) as exc:
            raise SnapshotError(f"{path}: corrupted atlas metadata: {exc}") from None
        if ncharts != atlas.ncharts:
            raise SnapshotError(f"{path}: {ncharts} chart files for {atlas.ncharts} charts")
        off += mlen
        for i in range(ncharts):
            if off + _LENGTH.size > len(data):
                raise SnapshotError(f"{path}: truncated at chart {i}")
            (size,) = _LENGTH.unpack_from(data, off)
            off += _LENGTH.size
            if off + size > len(data):
                raise SnapshotError(f"{path}: truncated at chart {i}")
            f = Field.from_bytes(data[off:off + size], source=f"{path}: chart {i}")
            off += size
            if f.ndim != obj.ndim or f.channels != obj.channels:
                raise SnapshotError(f"{path}: chart {i} does not match the atlas")
            want = atlas.warps[i]
            if (f.warp is None) != (want is None) or (
                    want is not None and f.warp.to_dict() != want.to_dict()):
                raise SnapshotError(f"{path}: chart {i}'s warp does not match the atlas's")
            obj.fields[i] = f
        if off != len(data):
            raise SnapshotError(f"{path}: {len(data) - off} bytes after the last chart")
        obj._nsamples, obj._nrejected = nsamples, nrejected
        return obj

    def __repr__(self) -> str:
        return (f"AtlasField(k={self.k}, d={self.d}, charts={self.atlas.ncharts}, "
                f"oriented={self.atlas.oriented}, channels={self.channels}, "
                f"nsamples={self.nsamples}, nstored={self.nstored})")


_NO_ROWS = np.empty(0, np.int64)
_NO_ROWS.setflags(write=False)
_ATLAS_MAGIC = b"FSATLAS\x00"
_ATLAS_VERSION = 1
_ATLAS_HEADER = struct.Struct("<8sIQ")  # magic, version, metadata length
_LENGTH = struct.Struct("<Q")
