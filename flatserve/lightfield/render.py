"""Rendering novel views: a camera's rays looked up in a light field.

Rendering is the paper's reconstruction (Sec. 5.2): the camera's rays (all
supersamples, in scanline order so that consecutive walks start next to each
other) become lines, lines become affine coordinates in the field's basis,
coordinates are embedded and located in the triangulation, and the values of
the simplex's vertices are blended with the barycentric weights (located in
serpentine order: odd fine scanlines reversed, so that every walk starts at
the previous ray's answer, including across line ends). Supersamples
are averaged into pixels. The same camera cast against the mesh is the ground
truth.

A pixel is *covered* when all its rays have trustworthy coordinates (they
round-trip: inside the basis chart) and lie inside the samples' convex hull.
Uncovered pixels average whatever rays of theirs have a value; pixels with
none get ``fill``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field

import numpy as np

from ..field import Chart, Field
from ..flats import Flats
from .camera import Camera

__all__ = ["Frame", "render_field", "render_truth", "frame_from_rays"]


@dataclass
class Frame:
    """A rendered image.

    Attributes
    ----------
    image : (H, W, C) float64
        Pixel values; pixels without any valued ray hold ``fill``.
    covered : (H, W) bool
        All rays of the pixel valued (in the chart and inside the hull).
    timings : dict of str to float
        Seconds per stage (``rays``, ``coordinates``, ``locate_interpolate``,
        ``resolve``, or ``cast`` for ground truth).
    ray_inside : (H*s * W*s,) bool
        Per supersample ray: valued.
    chart : flatserve.Chart or None
        The rays' chart (field renders, in raster order), for reuse by baselines.
    """

    image: np.ndarray
    covered: np.ndarray
    timings: dict = dc_field(default_factory=dict)
    ray_inside: np.ndarray | None = None
    chart: "Chart | None" = None

    @property
    def coverage(self) -> float:
        """Share of covered pixels."""
        return float(self.covered.mean()) if self.covered.size else 0.0

    @property
    def uncovered(self) -> float:
        """Share of pixels not covered."""
        return 1.0 - self.coverage

    @property
    def seconds(self) -> float:
        """Total of :attr:`timings`."""
        return float(sum(self.timings.values()))


def frame_from_rays(camera: Camera, values: np.ndarray, inside: np.ndarray, fill=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Resolve per-ray values (NaN or ``inside`` False = no value) into pixels.

    Parameters
    ----------
    camera : Camera
    values : (n, C) float
    inside : (n,) bool
    fill : float or (C,) float
        Value of pixels without any valued ray.

    Returns
    -------
    image : (H, W, C) float64
    covered : (H, W) bool
    """
    s = camera.side
    inside = np.asarray(inside, dtype=bool) & np.all(np.isfinite(values), axis=1)
    if inside.all():  # every ray valued (the common case): a plain mean, same numbers
        img = camera.resolve(values)
        covered = np.ones((camera.height, camera.width), dtype=bool)
        return img, covered
    img = camera.resolve(np.where(inside[:, None], values, 0.0), weights=inside.astype(np.float64))
    img = np.where(np.isnan(img), np.broadcast_to(np.asarray(fill, dtype=np.float64), img.shape), img)
    covered = inside.reshape(camera.height, s, camera.width, s).all(axis=(1, 3))
    return img, covered


def render_field(field, camera: Camera, *, fill=0.0, threads: int | None = None,
                 interpolant: str = "linear") -> Frame:
    """Render a camera's view from a light field.

    Parameters
    ----------
    field : flatserve.Field, or any field of the contract (an atlas field...)
        Lines in R^3 (k = 1, d = 3) with C channels.  An atlas field charts
        the rays inside its query (per chart): ``coordinates`` is then 0 and
        the frame has no ``chart``.
    camera : Camera
    fill : float or (C,) float
        Value of pixels with no valued ray.
    threads : int, optional
        Threads for coordinates and locate + interpolate (default all cores
        for big frames); the image does not depend on it.
    interpolant : {"linear", "gradient"}
        The field's (:meth:`flatserve.Field.query`): the paper's, or the
        cell's Taylor expansions with slopes fitted to the nearest samples.

    Returns
    -------
    Frame
        With timings ``rays``, ``coordinates``, ``locate_interpolate``, ``resolve``.
    """
    t0 = time.perf_counter()
    o, d = camera.rays()
    t_rays = time.perf_counter() - t0
    rays = Flats.from_rays(o, d)
    # located in serpentine order (each walk starts at the previous ray's answer)
    snake = _serpentine(np.arange(o.shape[0]), camera.width * camera.side)
    if not isinstance(field, Field):  # an atlas field (or any other of the contract):
        chart = None                    # each of its shards charts its own rays
        t1 = time.perf_counter()
        res = field.query(rays.take(snake), order="given", threads=threads,
                          interpolant=interpolant)
    else:
        chart = field.chart(rays, threads=threads)
        t1 = time.perf_counter()
        res = field.query(chart.take(snake), order="given", threads=threads,
                          interpolant=interpolant)
    values, inside = res.values[snake], res.inside[snake]  # the permutation is its own inverse
    t2 = time.perf_counter()
    img, covered = frame_from_rays(camera, values, inside, fill)
    t3 = time.perf_counter()
    t_coords = 0.0 if chart is None else chart.seconds
    return Frame(img, covered, {"rays": t_rays, "coordinates": t_coords,
                                "locate_interpolate": t2 - t1, "resolve": t3 - t2}, ray_inside=inside,
                 chart=chart)


def _serpentine(a: np.ndarray, width: int) -> np.ndarray:
    """Rows of a scanline raster (``width`` per line) with every odd line reversed.

    Boustrophedon order keeps consecutive queries next to each other across
    line ends too, so the located walks (each starting from the previous
    answer) stay short: the wrap from the end of one line to the start of the
    next is a walk across the whole image. Its own inverse.
    """
    r = a.reshape((a.shape[0] // width, width) + a.shape[1:]).copy()
    r[1::2] = r[1::2, ::-1]
    return r.reshape(a.shape)


def render_truth(scene, camera: Camera) -> Frame:
    """Ground truth: the camera's rays cast against the scene's mesh.

    Parameters
    ----------
    scene : Scene
    camera : Camera

    Returns
    -------
    Frame
        Every pixel covered; timings ``rays``, ``cast``, ``resolve``.
    """
    t0 = time.perf_counter()
    o, d = camera.rays()
    t1 = time.perf_counter()
    values = scene.shade(o, d)
    t2 = time.perf_counter()
    img = camera.resolve(values)
    t3 = time.perf_counter()
    covered = np.ones((camera.height, camera.width), dtype=bool)
    return Frame(img, covered, {"rays": t1 - t0, "cast": t2 - t1, "resolve": t3 - t2},
                 ray_inside=np.ones(o.shape[0], dtype=bool))
