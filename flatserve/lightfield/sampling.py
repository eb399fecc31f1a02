"""From a scene to a light field: the paper's samples, shaded, in a Field.

Shared by ``flatserve lightfield paper-figure``, the service's demo field and
the benchmark, so all three build the same field the same way.  The
360-degree light field (``flatserve lightfield orbit``): samples from eyes all
around (:func:`orbit_samples`) in an oriented covering atlas field
(:func:`build_atlas_field`).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from .camera import RaySamples, paper_samples, rotation_about, sphere_samples
from .mesh import box_mesh, icosphere, load_bunny, merge_meshes
from .scene import Checker, Scene

__all__ = ["BASIS_SCALE", "BUILD_CHUNK", "bunny_scene", "blocks_scene", "sample_scene",
           "orbit_samples", "build_field", "build_atlas_field", "BuildStats", "ProgressBar"]

#: Paper Sec. 5.2: the base simplex multiplied by 0.01.
BASIS_SCALE = 0.01
#: Rays per Field.add call (bounds memory of the coordinate computation).
BUILD_CHUNK = 100_000


def bunny_scene(channels: int = 1, cache_dir=None, **kwargs) -> Scene:
    """The paper's scene: the Stanford bunny in the unit box, diffuse shading."""
    return Scene(load_bunny(cache_dir), channels=channels, **kwargs)


def blocks_scene(channels: int = 1, **kwargs) -> Scene:
    """A procedural scene that is not the bunny: three primitives under a solid checker.

    A slab (0.7 x 0.25 x 0.5, turned 25 degrees about y), a sphere (radius
    0.28, an icosphere of 1,280 faces) resting on it and a pillar (0.12 x
    0.6 x 0.12) beside them, all inside the unit box, textured by a solid
    checkerboard (:class:`~flatserve.lightfield.scene.Checker`, cells of
    0.125, albedo 0.3 / 0.9), lit as the bunny.  Fixed once, before any
    light field of it was rendered: flat faces, a smooth curved surface,
    occlusions and sharp texture edges, none of them the bunny's.
    """
    slab = box_mesh((-0.35, -0.125, -0.25), (0.35, 0.125, 0.25))
    ball = icosphere(3, 0.28)
    pillar = box_mesh((-0.06, -0.3, -0.06), (0.06, 0.3, 0.06))
    eye = np.eye(3)
    mesh = merge_meshes(slab, ball, pillar, transforms=[
        (rotation_about("y", 25.0), (0.0, -0.3, 0.0)),
        (eye, (0.05, 0.1, 0.0)),
        (eye, (-0.38, -0.12, 0.3)),
    ])
    kwargs.setdefault("texture", Checker())
    return Scene(mesh, channels=channels, **kwargs)


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


def orbit_samples(scene: Scene, n: int, seed: int = 0, *, eyes: int | None = None
                  ) -> tuple[RaySamples, np.ndarray]:
    """``n`` rays from eyes all around the scene (:func:`~flatserve.lightfield.camera.sphere_samples`), shaded.

    Parameters
    ----------
    scene : Scene
    n : int
        Number of rays.
    seed : int
        Seed of the ray directions.
    eyes : int, optional
        Number of eyes (default ``ceil(sqrt(n))``).

    Returns
    -------
    samples : RaySamples
    values : (n, C) float64
    """
    samples = sphere_samples(n, np.random.default_rng(seed), eyes=eyes)
    return samples, scene.shade(samples.origins, samples.directions)


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
                chunk: int = BUILD_CHUNK, progress=None, tiles: int | str = "auto"):
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
    tiles : int or "auto"
        The chart's tiles (:class:`flatserve.Field` ``tiles``; the same answers
        bit for bit): by default one per core once the field is large enough
        (1.7x faster on 2 cores at the paper's 1M rays: docs/scaling.md).

    Returns
    -------
    field : flatserve.Field
    stats : BuildStats
        Rejected samples are those outside the basis chart; the build's seconds
        include the tiles' exchange.
    """
    from ..basis import Basis
    from ..field import Field

    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    kw = {} if variant is None else {"variant": variant}
    field = Field(Basis.around_axis(axis=2, scale=scale, **kw), channels=values.shape[1],
                  tiles=tiles)
    return field, _fill(field, origins, directions, values, chunk, progress)


def build_atlas_field(origins, directions, values, *, atlas=None, chunk: int = BUILD_CHUNK,
                      progress=None):
    """An oriented atlas field over rays in R^3, filled with samples.

    Parameters
    ----------
    origins, directions : (n, 3) float
        Sample rays (their direction is kept: oriented).
    values : (n, C) float
    atlas : flatserve.atlas.Atlas, optional
        Default ``Atlas.covering(1, 3, oriented=True)`` (32 charts: every
        direction; the unit of length fitted to the first batch, the
        library's and the service's default).
    chunk : int
        Rays per insertion batch.
    progress : callable(done, total), optional

    Returns
    -------
    field : flatserve.atlas_field.AtlasField
    stats : BuildStats
        Rejected samples are those no chart holds (none with a covering atlas).
    """
    from ..atlas import Atlas
    from ..atlas_field import AtlasField

    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    if atlas is None:
        atlas = Atlas.covering(1, 3, oriented=True)
    field = AtlasField(atlas, channels=values.shape[1])
    return field, _fill(field, origins, directions, values, chunk, progress)


def _fill(field, origins, directions, values, chunk: int, progress) -> BuildStats:
    """Add the rays to ``field`` (a Field or an AtlasField) ``chunk`` at a time."""
    from ..flats import Flats

    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
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
    field.settle()  # (a chart in tiles: the exchange the adds left pending)
    return BuildStats(n, accepted, rejected, duplicates, time.perf_counter() - t0)
