"""From a scene to a light field: the paper's samples, shaded, in a Field.

Shared by ``flatserve lightfield paper-figure``, the service's demo field and
the benchmarks, so all of them build the same field the same way.  Two
samplings: the paper's (:func:`sample_scene`, eyes on one side of the object,
one chart) and all around the object (:func:`sphere_eyes`,
:func:`sphere_samples`, :func:`sample_scene_sphere`: the 360 degree light field
of an oriented covering atlas, :func:`build_atlas_field`).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import SCREEN_HALF, RaySamples, paper_samples
from .mesh import load_bunny
from .scene import Scene

__all__ = ["BASIS_SCALE", "BUILD_CHUNK", "EYE_RADIUS", "TARGET_BOX", "TARGET_MARGIN", "bunny_scene", "sample_scene",
           "sphere_eyes", "sphere_samples", "sample_scene_sphere", "build_field",
           "build_atlas_field", "BuildStats", "ProgressBar"]

#: Paper Sec. 5.2: the base simplex multiplied by 0.01.
BASIS_SCALE = 0.01
#: Rays per Field.add call (bounds memory of the coordinate computation).
BUILD_CHUNK = 100_000
#: Distances of the eyes all around the object (:func:`sphere_eyes`): the
#: paper's eye depths (Sec. 5.2: 1.5 to 4.5 in front of the screen).
EYE_RADIUS = (1.5, 4.5)
#: Targets of :func:`sphere_samples`: the paper's screen [-1, 1]^2 made a cube.
TARGET_BOX = ((-SCREEN_HALF,) * 3, (SCREEN_HALF,) * 3)
#: :func:`sample_scene_sphere` aims at the mesh's box grown by this share of its side.
TARGET_MARGIN = 0.1


def bunny_scene(channels: int = 1, cache_dir=None, **kwargs) -> Scene:
    """The paper's scene: the Stanford bunny in the unit box, diffuse shading."""
    return Scene(load_bunny(cache_dir), channels=channels, **kwargs)


def sample_scene(scene: Scene, n: int, seed: int = 0) -> tuple[RaySamples, np.ndarray]:
    """The paper's n x n random light-field sampling of a scene (Fig. 11 left).

    Parameters
    ----------
    scene : Scene
    n : int
        Raster side: n^2 rays.
    seed : int
        Seed of the eye positions.

    Returns
    -------
    samples : RaySamples
    values : (n^2, C) float64
    """
    samples = paper_samples(n, np.random.default_rng(seed))
    return samples, scene.shade(samples.origins, samples.directions)


def sphere_eyes(n: int, rng: np.random.Generator, *, radius=EYE_RADIUS) -> np.ndarray:
    """Eye positions all around the origin: directions uniform on the sphere.

    Parameters
    ----------
    n : int
        Number of eyes.
    rng : numpy.random.Generator
    radius : float or (float, float)
        Distance from the origin: fixed, or uniform in ``[lo, hi]``.

    Returns
    -------
    (n, 3) float64
        Eye positions; ``|eye|`` in ``radius``.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise InvalidInputError(f"n: expected a non-negative integer, got {n!r}", "n")
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (2,)) if np.ndim(radius) == 0 \
        else as_array(radius, "radius", (2,))
    if not (0 < r[0] <= r[1] and np.isfinite(r).all()):
        raise InvalidInputError(f"radius: expected 0 < lo <= hi, got {tuple(r)}", "radius")
    u = rng.normal(size=(int(n), 3))
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), np.finfo(float).tiny)
    return u * rng.uniform(r[0], r[1], size=(int(n), 1))


def sphere_samples(n: int, rng: np.random.Generator, *, radius=EYE_RADIUS,
                   box=TARGET_BOX) -> tuple[np.ndarray, np.ndarray]:
    """Rays from eyes all around the object toward it (the 360 degree sampling).

    Each ray starts at its own eye (:func:`sphere_eyes`) and passes through
    its own target point drawn uniformly from ``box`` (the paper's sampling
    screen made a volume, so that every viewing direction sees it whole).

    Parameters
    ----------
    n : int
        Number of rays.
    rng : numpy.random.Generator
    radius : float or (float, float)
        Eye distances (:func:`sphere_eyes`).
    box : ((3,) float, (3,) float)
        Lower and upper corner of the targets' box.  A target that coincides
        with its eye is redrawn.

    Returns
    -------
    origins : (n, 3) float64
    directions : (n, 3) float64
        Unit directions.
    """
    lo = as_array(box[0], "box", (3,))
    hi = as_array(box[1], "box", (3,))
    if not (lo <= hi).all():
        raise InvalidInputError(f"box: expected lower <= upper corner, got {lo} and {hi}", "box")
    eyes = sphere_eyes(n, rng, radius=radius)
    d = rng.uniform(lo, hi, size=eyes.shape) - eyes
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    while (bad := norm[:, 0] < 1e-9).any():  # an eye on its target: redraw the target
        d[bad] = rng.uniform(lo, hi, size=(int(bad.sum()), 3)) - eyes[bad]
        norm = np.linalg.norm(d, axis=1, keepdims=True)
    return eyes, d / norm


def sample_scene_sphere(scene: Scene, n: int, seed: int = 0, *, radius=EYE_RADIUS,
                        margin: float = TARGET_MARGIN
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` rays from eyes all around a scene toward its mesh's box (:func:`sphere_samples`), shaded.

    Parameters
    ----------
    scene : Scene
    n : int
    seed : int
        Seed of the eyes and targets.
    radius : float or (float, float)
        Eye distances.
    margin : float
        The targets' box is the mesh's bounding box grown by this share of
        its longest side on every face.

    Returns
    -------
    origins, directions : (n, 3) float64
    values : (n, C) float64
    """
    lo, hi = scene.mesh.bounds
    pad = float(margin) * float((hi - lo).max())
    o, d = sphere_samples(n, np.random.default_rng(seed), radius=radius, box=(lo - pad, hi + pad))
    return o, d, scene.shade(o, d)


class ProgressBar:
    """A one-line text progress bar on a stream (stderr by default)."""

    def __init__(self, label: str, total: int, stream=None, width: int = 30):
        self.label, self.total, self.width = label, max(int(total), 1), width
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.perf_counter()

    def __call__(self, done: int, total: int | None = None) -> None:
        total = self.total if total is None else max(int(total), 1)
        frac = min(max(done / total, 0.0), 1.0)
        bar = "#" * int(frac * self.width)
        end = "\n" if done >= total else ""
        self.stream.write(f"\r{self.label} [{bar:<{self.width}}] {done:,}/{total:,} "
                          f"({time.perf_counter() - self.t0:.0f} s){end}")
        self.stream.flush()


@dataclass
class BuildStats:
    """How a field build went."""

    samples: int
    accepted: int
    rejected: int
    duplicates: int
    seconds: float


def build_field(origins, directions, values, *, scale: float = BASIS_SCALE, variant: str | None = None,
                chunk: int = BUILD_CHUNK, progress=None):
    """A Field over lines in R^3 with the paper's basis, filled with samples.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays.
    values : (n, C) float
    scale : float
        Tangent-simplex scale around the z-axis (Sec. 5.1).
    variant : str, optional
        Tangent variant (default the math module's default).
    chunk : int
        Rays per insertion batch.
    progress : callable(done, total), optional

    Returns
    -------
    field : flatserve.Field
    stats : BuildStats
        Rejected samples are those outside the basis chart.
    """
    from ..basis import Basis
    from ..field import Field

    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    kw = {} if variant is None else {"variant": variant}
    field = Field(Basis.around_axis(axis=2, scale=scale, **kw), channels=values.shape[1])
    n = values.shape[0]
    t0 = time.perf_counter()
    accepted = rejected = duplicates = 0
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        res = field.add_rays(origins[lo:hi], directions[lo:hi], values[lo:hi])
        accepted += res.accepted
        rejected += len(res.rejected)
        duplicates += res.duplicates
        if progress is not None:
            progress(hi, n)
    return field, BuildStats(n, accepted, rejected, duplicates, time.perf_counter() - t0)


def build_atlas_field(origins, directions, values, *, atlas=None, chunk: int = BUILD_CHUNK,
                      progress=None):
    """An oriented covering :class:`~flatserve.atlas.AtlasField` of rays, filled with samples.

    The 360 degree counterpart of :func:`build_field`: every ray direction
    lies inside some chart (:meth:`flatserve.atlas.Atlas.covering` with
    ``oriented=True``: the 6 icosahedral axes and their negatives).

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays (their orientation counts: a ray and its reverse see
        different surfaces).
    values : (n, C) float
    atlas : flatserve.atlas.Atlas, optional
        Default ``Atlas.covering(1, 3, oriented=True)``.
    chunk : int
        Rays per insertion batch.
    progress : callable(done, total), optional

    Returns
    -------
    field : flatserve.atlas.AtlasField
    stats : BuildStats
    """
    from ..atlas import Atlas, AtlasField
    from ..flats import Flats

    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    field = AtlasField(atlas if atlas is not None else Atlas.covering(1, 3, oriented=True),
                       channels=values.shape[1])
    n = values.shape[0]
    t0 = time.perf_counter()
    accepted = rejected = duplicates = 0
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        res = field.add(Flats.from_rays(origins[lo:hi], directions[lo:hi]), values[lo:hi])
        accepted += res.accepted
        rejected += len(res.rejected)
        duplicates += res.duplicates
        if progress is not None:
            progress(hi, n)
    return field, BuildStats(n, accepted, rejected, duplicates, time.perf_counter() - t0)
