"""Depth from a capture's own photographs, and novel views rendered through it.

On a rig whose cameras are far apart (all around an object, 15-25 degrees
between neighbours) a novel ray's neighbours in line space come from
photographs that saw the surface from different places: blending them ghosts
every surface off the blend's implicit focal surface, whatever the metric or
weights (``docs/capture-results.md``). Knowing where along the ray the
surface is removes the ghosting. This module gets that depth from the capture
alone and renders with it, the field still doing the interpolation:

* :func:`depth_map`: multi-view stereo by plane sweep. For each of a
  photograph's pixels, the depth along its ray at which the
  ``neighbours`` nearest cameras' photographs agree with it best (absolute
  differences averaged over a ``window`` x ``window`` patch; the best ``best``
  of the neighbours kept, so that a neighbour that cannot see the point does
  not veto it).
* the **depth channel** (:func:`depth_values`): a ray's depth as a value of
  its *line*, ``s = (x - c) . u`` for the surface point ``x``, the unit
  direction ``u`` and the rig's centre ``c``, so that the field can
  interpolate it at any ray (the same line from another origin has the same
  ``s``). A capture's field holds it as its last channel.
* :func:`guided_values` / :func:`render_guided`: a novel ray's depth
  interpolated by the field, refined by photo-consistency among candidates
  (the depths the nearest cameras' rays through the point report), then the
  colour blended from the rays of the nearest cameras through the surface
  point (each looked up in the field; seen only where that ray's own depth
  reaches the point), with the unstructured lumigraph's angle weights
  (Buehler et al. 2001).

:func:`flatserve.lightfield.rig.wants_depth` says when a rig is sparse enough for it to win (measured in
``docs/capture-results.md``: all around, not forward-facing).

>>> from flatserve.lightfield.capture import read_capture    # doctest: +SKIP
>>> from flatserve.lightfield.rig import depth_rig            # doctest: +SKIP
>>> cap = read_capture("scene")                               # doctest: +SKIP
>>> rig = depth_rig(cap.cameras)                              # doctest: +SKIP
"""
from __future__ import annotations

import math
import time
from typing import Callable, Sequence

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import PinholeCamera
from .rig import DepthRig

__all__ = ["mvs_view", "DEPTH_METHOD", "DEPTH_PLANES", "NEIGHBOURS", "WINDOW", "BEST", "MVS_SIDE", "VISIBILITY_TOL", "CANDIDATES",
           "BLEND", "DEPTH_FILTER", "sweep_range", "depth_map",
           "depth_values", "guided_values", "render_guided"]

#: Depths tried along each ray by :func:`depth_map` (uniform over the sweep range).
DEPTH_PLANES = 96
#: Cameras (nearest by eye) a photograph is compared with by :func:`depth_map`.
NEIGHBOURS = 4
#: Side of the square patch (pixels) over which :func:`depth_map` averages differences.
WINDOW = 5
#: Of the neighbours' patch differences, the best this many are averaged.
BEST = 2
#: Longest image side :func:`depth_map` works at (larger photographs are sampled down).
MVS_SIDE = 256
#: A camera sees a point when its ray's depth there is within this share of its distance.
VISIBILITY_TOL = 0.1
#: Cameras a novel ray's depth is checked against and its colour drawn from.
CANDIDATES = 6
#: Of the visible :data:`CANDIDATES`, the colours of this many nearest by angle are blended.
BLEND = 4
#: Cosine above which a camera's ray through a point is the ray itself (its eye on the ray).
ON_RAY_COS = 1.0 - 1e-12
#: Candidate depths closer than this share of the depth are one (tested once).
SAME_DEPTH = 0.002
#: Decimals the plane sweep's costs are rounded to before the least is taken.
COST_DIGITS = 9
#: Side (pixels) of the median filter over a rendered image's chosen depths.
DEPTH_FILTER = 3
#: What the depth channel's values depend on besides the photographs and poses: part of a
#: capture import's keys (a resumed import after this changes stores new batches).
DEPTH_METHOD = {"method": "plane-sweep", "version": 1, "planes": DEPTH_PLANES, "neighbours": NEIGHBOURS,
                "window": WINDOW, "best": BEST, "side": MVS_SIDE}
#: Rays per block of :func:`guided_values`.
BLOCK_RAYS = 16384
#: (ray, camera) pairs per block of :func:`guided_values` (fewer rays a block for a rig of
#: many cameras: its nearest-camera search is (rays x cameras)).
BLOCK_PAIRS = 1 << 20
#: A point closer to a camera's eye than this share of the eye's distance from the rig's
#: centre is at the eye (no ray from the camera through it).
ON_EYE = 1e-9


def sweep_range(camera: PinholeCamera, center) -> tuple[float, float]:
    """Depths :func:`depth_map` tries along a camera's rays.

    The scene is taken to lie within the camera's view at the rig's centre:
    ``D -/+ R`` for the distance ``D`` from the eye to ``center`` and ``R``
    the half-diagonal of the image's footprint there, ``D * hypot(w / 2fx,
    h / 2fy)``; the near end at least ``D / 10``.

    Returns
    -------
    near, far : float
    """
    D = float(np.linalg.norm(as_array(center, "center", (3,)) - camera.eye))
    if not D > 0:
        raise InvalidInputError("center: the rig's centre is at a camera's eye", "center")
    R = D * math.hypot(camera.width / (2 * camera.fx), camera.height / (2 * camera.fy))
    return max(D - R, D / 10), D + R


def _project(cam: PinholeCamera, p: np.ndarray):
    q = (p - cam.eye) @ cam.rotation
    z = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return cam.fx * q[:, 0] / z + cam.cx, cam.fy * q[:, 1] / z + cam.cy, z


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray):
    """``img`` (H, W) at image positions (pixel centres at +1/2); (values, inside)."""
    H, W = img.shape
    fx, fy = x - 0.5, y - 0.5
    ok = np.isfinite(fx) & np.isfinite(fy) & (fx >= -0.5) & (fy >= -0.5) & (fx <= W - 0.5) & (fy <= H - 0.5)
    fx = np.clip(np.where(ok, fx, 0.0), 0, W - 1)
    fy = np.clip(np.where(ok, fy, 0.0), 0, H - 1)
    x0 = np.minimum(fx.astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(fy.astype(np.int64), max(H - 2, 0))
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    ax, ay = fx - x0, fy - y0
    v = (img[y0, x0] * (1 - ax) * (1 - ay) + img[y0, x1] * ax * (1 - ay)
         + img[y1, x0] * (1 - ax) * ay + img[y1, x1] * ax * ay)
    return v, ok


def _grey(img: np.ndarray) -> np.ndarray:
    """Grey values of an (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) image; RGBA over black
    (transparent pixels match as the background they are stored as, a plain colour)."""
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 2:
        return img
    if img.shape[2] >= 3:
        g = img[..., :3].mean(axis=2)
        return g * img[..., 3] if img.shape[2] == 4 else g
    return img[..., 0]


def mvs_view(camera: PinholeCamera, image, side: int = MVS_SIDE) -> tuple[PinholeCamera, np.ndarray]:
    """A photograph as :func:`depth_map` compares it: grey, at most ``side`` pixels on its long side.

    Sampled down by a whole factor ``f`` (box average over ``f`` x ``f`` pixels, the
    right and bottom remainders cropped), with the camera scaled to match (one ray a pixel).

    Parameters
    ----------
    camera : PinholeCamera
    image : (H, W) or (H, W, C) float
        Its photograph, ``H, W`` the camera's.
    side : int

    Returns
    -------
    camera : PinholeCamera
        Of the small image (``supersample`` 1).
    grey : (h, w) float32
    """
    g = _grey(image)
    if g.shape != (camera.height, camera.width):
        raise InvalidInputError(f"image: expected ({camera.height}, {camera.width}) pixels as its camera, "
                                f"got {g.shape[:2]}", "image")
    f = max(1, int(math.ceil(max(camera.width, camera.height) / side)))
    H, W = (camera.height // f) * f, (camera.width // f) * f
    if f > 1:
        g = g[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))
    return camera.with_(width=W // f, height=H // f, fx=camera.fx / f, fy=camera.fy / f, cx=camera.cx / f,
                        cy=camera.cy / f, supersample=1), g.astype(np.float32)


def _box(a: np.ndarray, window: int) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(a, window, mode="nearest")


def depth_map(index: int, cameras: Sequence[PinholeCamera], image_of: Callable[[int], np.ndarray], *,
              center, planes: int = DEPTH_PLANES, neighbours: int = NEIGHBOURS, window: int = WINDOW,
              best: int = BEST, side: int = MVS_SIDE, views=None) -> np.ndarray:
    """Depth along each ray of camera ``index``'s photograph, by plane sweep.

    For each of ``planes`` depths ``t`` in :func:`sweep_range`, each pixel's
    point ``e + t u`` is projected into the ``neighbours`` cameras with the
    nearest eyes and their photographs sampled (bilinear, grey); the absolute
    differences with the pixel's own value are averaged over a ``window`` x
    ``window`` patch per neighbour (points outside a neighbour's image count 1),
    the ``best`` smallest averaged; the depth of the least is the pixel's.
    Works on the photographs as :func:`mvs_view` makes them (grey, at most
    ``side`` pixels on the long side), then read back at each pixel (nearest).

    Parameters
    ----------
    index : int
        The camera whose depth is wanted.
    cameras : sequence of PinholeCamera
        The capture's cameras.
    image_of : callable(int) -> (H, W, C) float array
        A camera's photograph (read when needed: at most ``neighbours + 1`` are
        asked for).
    center : (3,) float
        The rig's centre (:func:`sweep_range`).
    planes, neighbours, window, best, side : int
        :data:`DEPTH_PLANES`, :data:`NEIGHBOURS`, :data:`WINDOW`, :data:`BEST`,
        :data:`MVS_SIDE`.
    views : mutable mapping, optional
        Frame -> :func:`mvs_view`, read and filled: a caller computing every
        frame's map keeps the small grey views here (bounded by ``side``, not
        by the photographs) and each photograph is asked for once.

    Returns
    -------
    (H, W) float64
        Depth: distance along the unit ray from the eye, at the camera's own resolution.
    """
    cams = list(cameras)
    for name, v, lo in (("planes", planes, 2), ("neighbours", neighbours, 1), ("window", window, 1),
                        ("best", best, 1), ("side", side, 8)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise InvalidInputError(f"{name}: expected an integer >= {lo}, got {v!r}", name)
    if not (isinstance(index, (int, np.integer)) and 0 <= index < len(cams)) or len(cams) < 2:
        raise InvalidInputError(f"index: expected a camera of {len(cams)} (at least 2), got {index!r}", "index")
    center = as_array(center, "center", (3,))
    cam = cams[index]
    eyes = np.stack([c.eye for c in cams])
    dist = np.linalg.norm(eyes - cam.eye, axis=1)
    dist[index] = np.inf
    nb = [int(j) for j in np.argsort(dist)[:min(neighbours, len(cams) - 1)]]

    def view(j):
        if views is not None and j in views:
            return views[j]
        v = mvs_view(cams[j], image_of(j), side)
        if views is not None:
            views[j] = v
        return v

    small, me = view(index)
    others = [view(j) for j in nb]
    f = max(1, int(math.ceil(max(cam.width, cam.height) / side)))  # mvs_view's factor
    o, d = small.rays()
    h, w = small.height, small.width
    near, far = sweep_range(cam, center)
    ts = np.linspace(near, far, planes)
    ts = np.round(ts, COST_DIGITS)
    mine = me.reshape(-1)
    keep = min(best, len(nb))
    cost = np.empty((planes, h, w))
    for k, t in enumerate(ts):
        p = o + t * d
        per = np.empty((len(nb), h, w))
        for i, (oc, og) in enumerate(others):
            x, y, z = _project(oc, p)
            v, ok = _bilinear(og, x, y)
            e = np.where(ok & (z > 0), np.abs(v - mine), 1.0).reshape(h, w)
            per[i] = _box(e, window)
        per.sort(axis=0)
        cost[k] = per[:keep].mean(axis=0)
    # rounded before the least is taken: the same capture read from either format (poses that
    # differ by rounding) picks the same depths where costs tie; a tie (a plain background,
    # where every depth matches) takes the farthest depth, as a background is far: a near one
    # would stand in front of the scene for every ray that passes the object's edge
    rounded = np.round(cost, COST_DIGITS)
    depth = ts[planes - 1 - rounded[::-1].argmin(axis=0)]
    if (h, w) == (cam.height, cam.width):
        return depth
    rows = np.minimum(np.arange(cam.height) // f, h - 1)
    cols = np.minimum(np.arange(cam.width) // f, w - 1)
    return depth[rows[:, None], cols[None, :]]


def depth_values(origins, directions, depth, center) -> np.ndarray:
    """The depth channel: a ray's depth as a value of its line (Sec. 5.2's rays as lines).

    ``s = (o + t u - c) . u`` for origin ``o``, unit direction ``u``, depth
    ``t`` and the rig's centre ``c``: the surface point's position along the
    line measured from the line's point nearest ``c``. The same line from
    another origin has the same ``s``; the depth back is ``t = s + (c - o) . u``.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Unit directions.
    depth : (n,) float
    center : (3,) float

    Returns
    -------
    (n,) float64

    Examples
    --------
    >>> depth_values([[0, 0, -3]], [[0, 0, 1]], [2.5], [0, 0, 0])
    array([-0.5])
    """
    o = as_array(origins, "origins", (None, 3))
    d = as_array(directions, "directions", (o.shape[0], 3))
    t = as_array(depth, "depth", (o.shape[0],))
    c = as_array(center, "center", (3,))
    return np.einsum("ij,ij->i", o + t[:, None] * d - c, d)


def _depth_back(o, d, s, c):
    return s + np.einsum("...j,...j->...", c - o, d)


def guided_values(query: Callable, origins, directions, rig: DepthRig, *, candidates: int = CANDIDATES,
                  blend: int = BLEND, visibility_tol: float = VISIBILITY_TOL,
                  block_rays: int = BLOCK_RAYS, raster=None) -> tuple[np.ndarray, np.ndarray]:
    """Values at rays, through the depth channel (see the module's description).

    Per ray: its depth ``t0`` from the field (the last channel,
    :func:`depth_values`); the ``candidates`` cameras whose rays through the
    point ``p0`` at ``t0`` are nearest in angle to the ray; candidate depths
    ``t0`` and, per camera, the depth its ray through ``p0`` reports; the
    candidate at which the cameras that see the point (their ray's depth within
    ``visibility_tol`` of their distance to it) agree best (least spread of
    their colours; at least two seeing it, else ``t0``); finally the colours of
    the ``blend`` seeing cameras nearest in angle, weighted as the unstructured
    lumigraph's ``(1 - a / a_k) / a`` (``a`` the angle, ``a_k`` the next
    camera's). A camera whose eye is on the ray sees it whatever the depth (its
    ray is the ray: a capture's own rays answer their photographs). A ray no
    camera sees, or whose depth is not in front of its origin, keeps the
    field's own colour. Each ray asks the field ``1 + 2 * candidates`` times,
    and ``candidates`` more for each candidate depth not within
    :data:`SAME_DEPTH` of one tried: at most ``1 + candidates * (candidates +
    2)`` (49 with the defaults; 44 a ray measured on the sphere rig).

    Parameters
    ----------
    query : callable(origins, directions) -> (values (n, C + 1), inside (n,))
        The field at rays (unit directions), depth last; NaN or ``inside``
        False for no value.
    origins, directions : (n, 3) float
        The rays (unit directions).
    rig : DepthRig
    candidates, blend : int
        :data:`CANDIDATES`, :data:`BLEND` (``blend <= candidates``).
    visibility_tol : float
        :data:`VISIBILITY_TOL`.
    block_rays : int
        Rays per block.
    raster : (int, int), optional
        The rays are an image's, ``rows x cols`` in scanline order: the chosen
        depths are median-filtered over it (:data:`DEPTH_FILTER` pixels square)
        before the colours are blended, so that a ray whose test chose wrongly
        takes its neighbours' depth.

    Returns
    -------
    values : (n, C) float64
        NaN where the field has no value at the ray.
    inside : (n,) bool
    """
    o = as_array(origins, "origins", (None, 3))
    d = as_array(directions, "directions", (o.shape[0], 3))
    for name, v in (("candidates", candidates), ("blend", blend), ("block_rays", block_rays)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InvalidInputError(f"{name}: expected a positive integer, got {v!r}", name)
    if blend > candidates:
        raise InvalidInputError(f"blend: at most candidates ({candidates}), got {blend}", "blend")
    if not (isinstance(visibility_tol, (int, float)) and 0 < visibility_tol < 1):
        raise InvalidInputError(f"visibility_tol: expected a share in (0, 1), got {visibility_tol!r}",
                                "visibility_tol")
    if raster is not None:
        rows, cols = (int(x) for x in raster)
        if rows * cols != o.shape[0]:
            raise InvalidInputError(f"raster: {rows} x {cols} is not the {o.shape[0]} rays", "raster")
    K = min(candidates, rig.eyes.shape[0])
    tol = float(visibility_tol)
    # a block's (rays x eyes) arrays are bounded whatever the rig
    step = max(1, min(block_rays, BLOCK_PAIRS // rig.eyes.shape[0]))
    blocks = [slice(lo, lo + step) for lo in range(0, o.shape[0], step)]
    if not blocks:
        return np.empty((0, 0)), np.empty(0, dtype=bool)
    parts = [_choose(query, o[b], d[b], rig, K, tol) for b in blocks]
    first, inside, t = (np.concatenate([c[i] for c in parts]) for i in range(3))
    del parts
    if raster is not None and DEPTH_FILTER > 1:
        t = _nan_median(t.reshape(rows, cols), DEPTH_FILTER).reshape(-1)
    values = np.concatenate([_blend(query, o[b], d[b], t[b], first[b], inside[b], rig, K, min(blend, K), tol)
                             for b in blocks])
    return values, inside


def _nearest(eyes, p, d, K: int) -> np.ndarray:
    """Per ray, the ``K`` eyes whose rays through its point ``p`` are nearest in angle to it (n, K)."""
    v = p[:, None, :] - eyes[None]
    v /= np.maximum(np.linalg.norm(v, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("nkj,nj->nk", v, d)
    if K >= eyes.shape[0]:
        return np.argsort(-cos, axis=1)
    return np.argpartition(-cos, K - 1, axis=1)[:, :K]


def _seen(query, o, d, p, nb, rig: DepthRig, tol: float, C: int):
    """Colours (n, K, C) of points ``p`` from cameras ``nb`` (NaN: not seen there), and per
    camera where its ray through ``p`` says the surface is, as a depth along ``(o, d)``.
    The ``n * K`` cameras' rays are asked of the field in one query."""
    n, K = nb.shape
    e = rig.eyes[nb]  # (n, K, 3)
    ray = p[:, None, :] - e
    dist = np.linalg.norm(ray, axis=2)
    away = dist > ON_EYE * np.maximum(np.linalg.norm(e - rig.center, axis=2), 1e-300)
    # a point at the eye has no ray from it: not seen (the query's own direction is asked)
    u = np.where(away[:, :, None], ray / np.where(away, dist, 1.0)[:, :, None], d[:, None, :])
    vals, ok = query(e.reshape(-1, 3), u.reshape(-1, 3))
    vals = np.asarray(vals, dtype=np.float64).reshape(n, K, -1)
    ok = np.asarray(ok, dtype=bool).reshape(n, K) & np.isfinite(vals).all(axis=2) & away
    dep = np.where(ok, _depth_back(e, u, np.where(ok, vals[:, :, -1], 0.0), rig.center), np.nan)
    # a camera whose eye the ray passes through sees the ray's own first surface
    # whatever the depth (the unstructured lumigraph's epipole consistency)
    through = np.einsum("nkj,nj->nk", u, d) > ON_RAY_COS
    vis = ok & ((np.abs(dep - dist) < tol * dist) | through)
    cols = np.where(vis[:, :, None], vals[:, :, :-1], np.nan)
    q = e + np.nan_to_num(dep)[:, :, None] * u
    reach = np.where(ok, np.einsum("nkj,nj->nk", q - o[:, None, :], d), np.nan)
    return cols, reach


def _answer(query, o, d):
    vals, ok = query(o, d)
    vals = np.asarray(vals, dtype=np.float64)
    if vals.ndim != 2 or vals.shape[0] != o.shape[0] or vals.shape[1] < 2:
        raise InvalidInputError(f"query: expected values of shape ({o.shape[0]}, C + 1), colours and the "
                                f"depth channel last, got {vals.shape}", "query")
    return vals, np.asarray(ok, dtype=bool) & np.isfinite(vals).all(axis=1)


def _choose(query, o, d, rig: DepthRig, K: int, tol: float):
    """Per ray: the field's values (colours, depth), whether it has them, and the depth the
    candidates' test chooses (NaN: none; the ray keeps the field's colour)."""
    n = o.shape[0]
    first, inside = _answer(query, o, d)
    t = np.full(n, np.nan)
    rows = np.flatnonzero(inside)
    t[rows] = _depth_back(o[rows], d[rows], first[rows, -1], rig.center)
    rows = rows[t[rows] > 0]  # a surface behind the eye is no depth to test
    if rows.size == 0:
        return first, inside, t
    C = first.shape[1] - 1
    o, d, t0 = o[rows], d[rows], t[rows]
    m = rows.size
    p0 = o + t0[:, None] * d
    nb = _nearest(rig.eyes, p0, d, K)
    cols0, reach = _seen(query, o, d, p0, nb, rig, tol, C)
    T = np.concatenate([t0[:, None], np.where(np.isfinite(reach) & (reach > 0), reach, t0[:, None])], axis=1)
    best_cost, best_t = np.full(m, np.inf), t0.copy()
    same = SAME_DEPTH * np.abs(T)
    # a candidate within SAME_DEPTH of one already tried is that one (not asked again);
    # the others of every candidate are asked of the field in one query
    picks = [np.arange(m)] + [np.flatnonzero((np.abs(T[:, c, None] - T[:, :c]) > same[:, c, None]).all(axis=1))
                              for c in range(1, T.shape[1])]
    more = np.concatenate(picks[1:])
    if more.size:
        at = o[more] + np.concatenate([T[pk, c] for c, pk in enumerate(picks) if c])[:, None] * d[more]
        split = np.cumsum([pk.size for pk in picks[1:]])[:-1]
        rest = np.split(_seen(query, o[more], d[more], at, nb[more], rig, tol, C)[0], split)
    else:
        rest = [cols0[:0]] * (T.shape[1] - 1)
    for c, pick in enumerate(picks):
        if pick.size == 0:
            continue
        cols = cols0 if c == 0 else rest[c - 1]
        count = np.isfinite(cols[:, :, 0]).sum(axis=1)
        spread = np.nansum(np.nanstd(np.where(count[:, None, None] >= 2, cols, 0.0), axis=1), axis=1)
        cost = np.where(count >= 2, spread, np.inf if c else 1e300)
        if c == 0:
            cost = cost - 1e-3  # the field's own depth wins a tie
        better = cost < best_cost[pick]
        best_cost[pick[better]] = cost[better]
        best_t[pick[better]] = T[pick[better], c]
    t[rows] = best_t
    return first, inside, t


def _blend(query, o, d, t, first, inside, rig: DepthRig, K: int, B: int, tol: float):
    """The colours at depths ``t``: the ``B`` seeing cameras of the ``K`` nearest in angle,
    the unstructured lumigraph's weights; the field's own colour where none sees or ``t``
    is NaN."""
    C = first.shape[1] - 1
    values = np.where(inside[:, None], first[:, :-1], np.nan)
    rows = np.flatnonzero(inside & np.isfinite(t))
    if rows.size == 0:
        return values
    o, d, t = o[rows], d[rows], t[rows]
    n = rows.size
    p = o + t[:, None] * d
    nb = _nearest(rig.eyes, p, d, K)
    cols, _ = _seen(query, o, d, p, nb, rig, tol, C)
    v = p[:, None, :] - rig.eyes[nb]
    v /= np.maximum(np.linalg.norm(v, axis=2, keepdims=True), 1e-300)
    a = np.arccos(np.clip(np.einsum("nkj,nj->nk", v, d), -1.0, 1.0))
    a = np.where(np.isfinite(cols[:, :, 0]), a, np.inf)
    order = np.argsort(a, axis=1)
    a = np.take_along_axis(a, order, axis=1)
    cols = np.take_along_axis(cols, order[:, :, None], axis=1)
    finite = np.isfinite(a[:, :B])
    nxt = a[:, B:B + 1] if K > B else np.full((n, 1), np.inf)
    widest = np.max(np.where(finite, a[:, :B], 0.0), axis=1, keepdims=True)
    nxt = np.where(np.isfinite(nxt), nxt, 1.5 * widest + 1e-9)
    w = np.clip(1.0 - a[:, :B] / nxt, 0.0, None) / np.maximum(a[:, :B], 1e-6)
    w = np.where(finite, w, 0.0)
    total = w.sum(axis=1)
    mixed = np.einsum("nk,nkc->nc", w, np.nan_to_num(cols[:, :B])) / np.where(total > 0, total, 1.0)[:, None]
    values[rows] = np.where((total > 0)[:, None], mixed, values[rows])
    return values


def _nan_median(img: np.ndarray, size: int) -> np.ndarray:
    """Median over ``size`` x ``size`` neighbourhoods of the finite values (NaN stays NaN)."""
    r = size // 2
    H, W = img.shape
    pad = np.pad(img, r, mode="constant", constant_values=np.nan)
    stack = np.stack([pad[i:i + H, j:j + W] for i in range(size) for j in range(size)])
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out = np.nanmedian(stack, axis=0)
    return np.where(np.isfinite(img), out, np.nan)


def render_guided(field, camera, rig: DepthRig, *, fill=0.0, threads: int | None = None, **options):
    """Render a camera's view of a capture's field through its depth channel.

    Parameters
    ----------
    field : flatserve.atlas_field.AtlasField or any field of the contract
        Oriented lines in R^3 whose last channel is the depth channel
        (:func:`depth_values`).
    camera : Camera or PinholeCamera
    rig : DepthRig
    fill : float or (C,) float
        Value of pixels with no valued ray.
    threads : int, optional
        The field's query threads.
    **options
        :func:`guided_values`' ``candidates``, ``blend``, ``visibility_tol``.

    Returns
    -------
    flatserve.lightfield.render.Frame
        Of the colour channels; timings ``rays``, ``guided``, ``resolve``.
    """
    from ..flats import Flats
    from .render import Frame, frame_from_rays

    def query(o, d):
        r = field.query(Flats.from_rays(o, d), threads=threads)
        return r.values, r.inside

    t0 = time.perf_counter()
    o, d = camera.rays()
    t1 = time.perf_counter()
    s = camera.side
    values, inside = guided_values(query, o, d, rig, raster=(camera.height * s, camera.width * s), **options)
    t2 = time.perf_counter()
    img, covered = frame_from_rays(camera, values, inside, fill)
    t3 = time.perf_counter()
    return Frame(img, covered, {"rays": t1 - t0, "guided": t2 - t1, "resolve": t3 - t2}, ray_inside=inside)
