"""From a scene to a light field: the paper's samples, shaded, in a Field.

Shared by ``flatserve lightfield paper-figure``, the service's demo field and
the benchmark, so all three build the same field the same way.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from .camera import RaySamples, paper_samples
from .mesh import load_bunny
from .scene import Scene

__all__ = ["BASIS_SCALE", "BUILD_CHUNK", "bunny_scene", "sample_scene", "build_field",
           "BuildStats", "ProgressBar"]

#: Paper Sec. 5.2: the base simplex multiplied by 0.01.
BASIS_SCALE = 0.01
#: Rays per Field.add call (bounds memory of the coordinate computation).
BUILD_CHUNK = 100_000


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
