"""Scenes: a mesh, ray casting with CGAL's AABB tree, diffuse shading.

Casting is native (``native/raycast.hpp``: ``CGAL::AABB_tree`` over the
triangles, ``first_intersection`` per ray, batched, GIL released, threads);
shading is NumPy: Lambert with one fixed directional light plus an ambient
term, normals interpolated from vertex normals (smooth) or per face, turned
toward the viewer (meshes need not be consistently oriented). Rays that miss
get the background value.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import _native
from .._validate import as_array
from ..errors import InvalidInputError
from .mesh import Mesh

__all__ = ["RayHits", "Scene", "Checker", "DEFAULT_LIGHT", "DEFAULT_AMBIENT", "BARYCENTRIC_EPS"]

#: Direction *toward* the light (world coordinates, normalised on use):
#: from above, left and in front of eyes at negative z.
DEFAULT_LIGHT = (-0.4, 0.6, -0.7)
#: Share of the albedo seen where the light does not reach.
DEFAULT_AMBIENT = 0.15
#: Guard for barycentric coordinates of hits on (near) degenerate triangles.
BARYCENTRIC_EPS = 1e-300


@dataclass(frozen=True)
class RayHits:
    """First hits of a batch of rays.

    Attributes
    ----------
    t : (n,) float64
        Ray parameter of the hit (point = origin + t * direction), +inf on a miss.
    face : (n,) int64
        Index of the hit triangle, -1 on a miss.
    """

    t: np.ndarray
    face: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(n,) bool."""
        return self.face >= 0


@dataclass(frozen=True)
class Checker:
    """A solid checkerboard texture: albedo by the parity of a cubic cell.

    ``albedo(p) = high`` where ``floor(px / period) + floor(py / period) +
    floor(pz / period)`` is even, else ``low`` (the same in every channel).

    Parameters
    ----------
    period : float
        Side of a cell.
    low, high : float
        Albedos in [0, 1].
    """

    period: float = 0.125
    low: float = 0.3
    high: float = 0.9

    def __call__(self, points: np.ndarray, channels: int) -> np.ndarray:
        """(n, 3) points -> (n, channels) albedo."""
        cells = np.floor(np.asarray(points, dtype=np.float64) / self.period).astype(np.int64)
        even = (cells.sum(axis=1) % 2) == 0
        return np.repeat(np.where(even, self.high, self.low)[:, None], channels, axis=1)


def _caster(mesh: Mesh):
    return _native.RayCaster(mesh.vertices, mesh.faces)


@dataclass
class Scene:
    """A mesh lit by one directional light, seen against a background.

    Parameters
    ----------
    mesh : Mesh
    channels : int
        1 (grey) or 3 (RGB).
    albedo : (C,) float, optional
        Surface colour in [0, 1] (default 0.9 grey or a warm tan in RGB).
    background : (C,) float, optional
        Value of rays that miss (default 0).
    light : (3,) float
        Direction toward the light.
    ambient : float
        Ambient share in [0, 1].
    smooth : bool
        Interpolate vertex normals (True) or use face normals.
    texture : callable(points (n, 3), channels) -> (n, C), optional
        Albedo at the hit points (e.g. :class:`Checker`), replacing ``albedo``.
    threads : int
        Threads for casting (0: all cores).
    """

    mesh: Mesh
    channels: int = 1
    albedo: np.ndarray | None = None
    background: np.ndarray | None = None
    light: tuple = DEFAULT_LIGHT
    ambient: float = DEFAULT_AMBIENT
    smooth: bool = True
    texture: Callable | None = None
    threads: int = 0
    _rc: object = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if self.channels not in (1, 3):
            raise InvalidInputError(f"channels: expected 1 or 3, got {self.channels!r}", "channels")
        C = self.channels
        if self.albedo is None:
            self.albedo = np.full(C, 0.9) if C == 1 else np.array([0.95, 0.78, 0.55])
        if self.background is None:
            self.background = np.zeros(C)
        self.albedo = as_array(np.broadcast_to(self.albedo, (C,)), "albedo", (C,))
        self.background = as_array(np.broadcast_to(self.background, (C,)), "background", (C,))
        light = as_array(self.light, "light", (3,))
        if not np.linalg.norm(light) > 0:
            raise InvalidInputError("light: must be a non-zero direction", "light")
        self._light = light / np.linalg.norm(light)
        if not 0 <= self.ambient <= 1:
            raise InvalidInputError(f"ambient: expected a share in [0, 1], got {self.ambient!r}", "ambient")
        self._rc = _caster(self.mesh)
        self._face_n = self.mesh.face_normals()
        self._vert_n = self.mesh.vertex_normals() if self.smooth else None

    def cast(self, origins, directions) -> RayHits:
        """First hits of rays.

        Parameters
        ----------
        origins, directions : (n, 3) float
            Rays as rows; only t >= 0 counts (the half-line from the origin).

        Returns
        -------
        RayHits
        """
        o = as_array(origins, "origins", (None, 3))
        d = as_array(directions, "directions", (o.shape[0], 3))
        t, face = self._rc.cast(o, d, int(self.threads))
        return RayHits(t=np.asarray(t), face=np.asarray(face))

    def normals_at(self, points, face) -> np.ndarray:
        """Shading normals at points on given faces.

        Parameters
        ----------
        points : (n, 3) float
            Points on the triangles.
        face : (n,) int64
            Triangle indices (all valid).

        Returns
        -------
        (n, 3) float64, unit (or zero on degenerate input).
        """
        if self._vert_n is None:
            return self._face_n[face]
        tri = self.mesh.faces[face]
        a, b, c = (self.mesh.vertices[tri[:, i]] for i in range(3))
        v0, v1, v2 = b - a, c - a, points - a
        d00 = np.einsum("ij,ij->i", v0, v0)
        d01 = np.einsum("ij,ij->i", v0, v1)
        d11 = np.einsum("ij,ij->i", v1, v1)
        d20 = np.einsum("ij,ij->i", v2, v0)
        d21 = np.einsum("ij,ij->i", v2, v1)
        den = d00 * d11 - d01 * d01
        den = np.where(np.abs(den) > BARYCENTRIC_EPS, den, 1.0)
        wb = (d11 * d20 - d01 * d21) / den
        wc = (d00 * d21 - d01 * d20) / den
        wa = 1.0 - wb - wc
        n = (wa[:, None] * self._vert_n[tri[:, 0]] + wb[:, None] * self._vert_n[tri[:, 1]]
             + wc[:, None] * self._vert_n[tri[:, 2]])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        face_n = self._face_n[face]
        return np.where(length > 0, n / np.where(length > 0, length, 1.0), face_n)

    def shade(self, origins, directions) -> np.ndarray:
        """Colour of each ray: diffuse shading at its first hit, else background.

        Parameters
        ----------
        origins, directions : (n, 3) float

        Returns
        -------
        (n, C) float64 in [0, 1] for albedo and background in [0, 1].
        """
        o = as_array(origins, "origins", (None, 3))
        d = as_array(directions, "directions", (o.shape[0], 3))
        hits = self.cast(o, d)
        out = np.broadcast_to(self.background, (o.shape[0], self.channels)).copy()
        h = hits.hit
        if h.any():
            p = o[h] + hits.t[h, None] * d[h]
            n = self.normals_at(p, hits.face[h])
            # turn normals toward the viewer: the side the ray comes from
            flip = np.einsum("ij,ij->i", n, d[h]) > 0
            n[flip] = -n[flip]
            lambert = np.clip(n @ self._light, 0.0, None)
            shade = self.ambient + (1.0 - self.ambient) * lambert
            albedo = self.albedo[None, :] if self.texture is None else self.texture(p, self.channels)
            out[h] = shade[:, None] * albedo
        return out
