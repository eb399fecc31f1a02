"""Grassmannian geometry: principal angles, frames, coverings, blending weights.

The geometry under an :class:`~flatserve.atlas.Atlas`, with no charts in it:
how far apart two k-subspaces of R^d are, Haar-random subspaces, greedy covers
of the Grassmannian and their measured covering radius, the icosahedral axes
that cover the sphere of directions, and the bump that blends charts.

Angles
------
The principal angles between the direction spaces ``span(A_C)`` and
``span(A_F)`` (orthonormal ``A``, (d, k)) are the arccosines of the singular
values of ``A_C^T A_F``; the largest one is ``arccos(sigma_min)``.  The
non-zero principal angles of two k-subspaces equal those of their orthogonal
complements, so the smaller of ``A`` (k columns) and ``N`` (d-k columns) is
used (:func:`use_normals`).  Oriented lines (rays, k = 1) use the angle
between the unit directions (``arccos(a_C . a_F)``, in [0, 180] degrees): a
centre and its negative are different charts.

Coverings are pure functions of their seeded arguments and cached
(:func:`cover_frames`, :func:`cover_radius`): an atlas built again neither
searches nor measures again.

Example
-------
>>> import numpy as np
>>> from flatserve.grassmann import haar_frames, max_principal_angle
>>> rng = np.random.default_rng(0)
>>> C, F = haar_frames(3, 4, 2, rng), haar_frames(5, 4, 2, rng)
>>> max_principal_angle(C, F).shape             # (flats, centres), radians
(5, 3)
"""
from __future__ import annotations

import functools
import math

import numpy as np

from . import flats as _flats
from .embedding import row_product
from .flats import Flats

__all__ = [
    "GEODESIC_AXES",
    "ICOSAHEDRON_AXES",
    "bump",
    "complement",
    "cos2_max_angle",
    "cover_frames",
    "cover_radius",
    "covering_radius",
    "greedy_cover",
    "haar_frames",
    "max_principal_angle",
    "orientation_frames",
    "use_normals",
]

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


def use_normals(k: int, d: int) -> bool:
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
        normals = use_normals(k, d)
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


def cos2_max_angle(C: np.ndarray, F: np.ndarray) -> np.ndarray:
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
        out[:, c] = np.arccos(np.sqrt(cos2_max_angle(C[c], F)))
    return out


def complement(C: np.ndarray) -> np.ndarray:
    """Orthonormal frame (d, d-j) of the orthogonal complement of span(C) (d, j)."""
    d, j = C.shape
    _, V = np.linalg.eigh(C @ C.T)
    return V[:, : d - j]


def greedy_cover(T: np.ndarray, radius: float, first: np.ndarray) -> list[np.ndarray]:
    """Farthest-point centres among frames ``T`` (n, d, j), starting at ``first``.

    Adds the frame farthest (largest principal angle) from every centre so
    far until all of ``T`` is closer than ``radius`` (radians) to a centre.
    """
    centres = [first]
    best = cos2_max_angle(first, T)
    cos2r = math.cos(radius) ** 2
    while best.min() < cos2r:
        i = int(np.argmin(best))
        centres.append(T[i])
        np.maximum(best, cos2_max_angle(T[i], T), out=best)
    return centres


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@functools.lru_cache(maxsize=32)
def cover_frames(k: int, d: int, train_deg: float, seed: int, n_train: int) -> np.ndarray:
    """Centre frames of a covering of the k-subspaces of R^d (cached, read only).

    For lines and planes in R^3 the 16 :data:`GEODESIC_AXES`; otherwise a
    greedy farthest-point cover (:func:`greedy_cover`) of ``n_train``
    Haar-random subspaces (seeded), started at the span of the last axes,
    until each is within ``train_deg`` degrees of a centre.

    Returns
    -------
    ndarray, shape (c, d, j)
        ``j`` columns: direction frames, or normal frames when
        :func:`use_normals`.
    """
    j = d - k if use_normals(k, d) else k
    if j == 0:
        return _frozen(np.zeros((1, d, 0)))
    if (k, d) in ((1, 3), (2, 3)):
        return _frozen(GEODESIC_AXES[:, :, None].copy())
    rng = np.random.default_rng(seed)
    T = haar_frames(n_train, d, j, rng)
    first = np.eye(d)[:, d - j:]
    return _frozen(np.stack(greedy_cover(T, math.radians(train_deg), first)))


def covering_radius(frames, *, oriented: bool = False, n: int = 200_000, seed: int = 1,
                    return_worst: bool = False, batch: int = 50_000):
    """Largest angle (degrees) of ``n`` Haar-random orientations to the nearest centre.

    Parameters
    ----------
    frames : ndarray, shape (c, d, j)
        The centres (for oriented centres their signed unit directions, j = 1).
    oriented : bool
        Sample directions uniformly on the sphere and measure signed angles.
    n, seed : int
        The seeded sample measured.
    return_worst : bool
        Also return the frame of the orientation farthest from every centre.
    batch : int
        Orientations drawn at a time (memory).

    Returns
    -------
    float, or (float, ndarray (d, j)) with the worst orientation's frame
    """
    rng = np.random.default_rng(seed)
    c, d, j = frames.shape
    worst_c, worst_f = 2.0, None
    for start in range(0, n, batch):
        m = min(batch, n - start)
        if oriented:
            v = rng.standard_normal((m, d))
            F = (v / np.linalg.norm(v, axis=1, keepdims=True))[:, :, None]
            best = (F[:, :, 0] @ frames[:, :, 0].T).max(axis=1)
        else:
            F = haar_frames(m, d, j, rng)
            best = np.max([np.sqrt(cos2_max_angle(C, F)) for C in frames], axis=0)
        i = int(np.argmin(best))
        if best[i] < worst_c:
            worst_c, worst_f = float(best[i]), F[i]
    deg = float(np.degrees(np.arccos(np.clip(worst_c, -1.0, 1.0))))
    return (deg, worst_f) if return_worst else deg


@functools.lru_cache(maxsize=32)
def cover_radius(k: int, d: int, oriented: bool, train_deg: float, seed: int, n_train: int,
                 check_n: int) -> float:
    """The covering radius (degrees) of :func:`cover_frames`, measured once (cached).

    Measured by :func:`covering_radius` on ``check_n`` fresh orientations
    (seed ``seed + 1``) against the centres and, when ``oriented``, their
    negatives (lines in R^3: 0.05 s; 3-flats in R^5, 329 charts: about 17 s).
    """
    C = cover_frames(k, d, train_deg, seed, n_train)
    if oriented:
        C = np.concatenate([C, -C])
    return covering_radius(C, oriented=oriented, n=check_n, seed=seed + 1)
