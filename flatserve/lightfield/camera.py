"""Pinhole cameras and the paper's random light-field sampling.

Conventions (docs/design.md, "Light fields"; paper Sec. 5.2 with the axes renamed so that the basis
is built around the z-axis): the object sits at the origin, the fixed sampling
screen is the plane z = 0, eyes lie at negative z looking toward +z, image up
is +y and image right is +x.

A camera's orientation is a rotation matrix whose *columns* are the image's
right, up and forward directions in world coordinates. The image plane spans
[-1, 1] horizontally (and [-h/w, h/w] vertically) at distance ``focal`` in
front of the eye: the default camera (eye (0, 0, -3), focal 3) sees exactly
the sampling screen [-1, 1]^2 at z = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from ..flats import MAX_ENTRY

__all__ = [
    "Camera",
    "RaySamples",
    "paper_samples",
    "sphere_samples",
    "fibonacci_sphere",
    "rotation_about",
    "EYE_LOW",
    "EYE_HIGH",
    "SCREEN_HALF",
    "DEFAULT_EYE",
    "DEFAULT_FOCAL",
    "DEFAULT_SUPERSAMPLE",
    "ORTHONORMAL_TOL",
    "ORBIT_EYE_RADIUS",
    "ORBIT_RADIUS",
]

#: Paper Sec. 5.2: eyes uniform in [-1, 1]^2 x [-4.5, -1.5].
EYE_LOW = (-1.0, -1.0, -4.5)
EYE_HIGH = (1.0, 1.0, -1.5)
#: Half the side of the square sampling screen at z = 0.
SCREEN_HALF = 1.0
#: Default camera: centre of the eye box, seeing the whole sampling screen.
DEFAULT_EYE = (0.0, 0.0, -3.0)
DEFAULT_FOCAL = 3.0
#: Rays per pixel (a square number: 4 = 2 x 2).
DEFAULT_SUPERSAMPLE = 4
#: How far from orthonormal a camera rotation may be.
ORTHONORMAL_TOL = 1e-6
#: 360-degree sampling (:func:`sphere_samples`): eyes on the sphere of this
#: radius about the origin (the distance of the default camera) ...
ORBIT_EYE_RADIUS = 3.0
#: ... with rays through the ball of this radius about the origin: it holds
#: the unit box [-1/2, 1/2]^3 the scenes are normalised to (radius 0.866).
ORBIT_RADIUS = 1.0


@dataclass(frozen=True)
class RaySamples:
    """Rays with their place on the fixed sampling screen.

    Attributes
    ----------
    origins : (n, 3) float64
        Eye of each ray.
    directions : (n, 3) float64
        Unit direction from the eye through its screen pixel.
    screen : (n, 3) float64
        The screen pixel's centre (z = 0); of :func:`sphere_samples`, the
        ray's point closest to the origin.
    shape : (int, int)
        Raster shape (rows, columns); ray ``i`` is pixel ``divmod(i, columns)``,
        row 0 at the top (+y); ``(1, n)`` for samples without a raster.
    """

    origins: np.ndarray
    directions: np.ndarray
    screen: np.ndarray
    shape: tuple[int, int]


def paper_samples(n: int, rng: np.random.Generator, *, eye_low=EYE_LOW, eye_high=EYE_HIGH,
                  screen_half: float = SCREEN_HALF) -> RaySamples:
    """The paper's random light-field sampling (Sec. 5.2, Fig. 11 left).

    One ray per pixel of a fixed n x n raster on the screen z = 0, each from
    its own eye drawn uniformly from the box ``[eye_low, eye_high]``.

    Parameters
    ----------
    n : int
        Raster side (n^2 rays).
    rng : numpy.random.Generator
        Source of the eye positions.
    eye_low, eye_high : (3,) float
        Corners of the eye box.
    screen_half : float
        The raster covers [-screen_half, screen_half]^2.

    Returns
    -------
    RaySamples
        n^2 rays in scanline order.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise InvalidInputError(f"n: expected a positive integer, got {n!r}", "n")
    lo = as_array(eye_low, "eye_low", (3,))
    hi = as_array(eye_high, "eye_high", (3,))
    c = (np.arange(n) + 0.5) / n * 2 - 1
    xs, ys = np.meshgrid(c * screen_half, -c * screen_half)  # row 0 at the top
    screen = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    eyes = rng.uniform(lo, hi, size=(n * n, 3))
    d = screen - eyes
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return RaySamples(origins=eyes, directions=d, screen=screen, shape=(int(n), int(n)))


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly evenly spread unit vectors (the Fibonacci sphere).

    Point ``i`` has ``z = 1 - (2 i + 1) / n`` and longitude ``i`` times the
    golden angle ``pi (3 - sqrt 5)``: equal-area latitude bands, each holding
    one point.

    Returns
    -------
    (n, 3) float64
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise InvalidInputError(f"n: expected a positive integer, got {n!r}", "n")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * (math.pi * (3.0 - math.sqrt(5.0)))
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def sphere_samples(n: int, rng: np.random.Generator, *, eyes: int | None = None,
                   eye_radius: float = ORBIT_EYE_RADIUS, radius: float = ORBIT_RADIUS) -> RaySamples:
    """Rays from eyes all around the object (the 360-degree light field's samples).

    ``eyes`` eyes on a Fibonacci sphere (:func:`fibonacci_sphere`) of radius
    ``eye_radius`` about the origin; from each eye ``n / eyes`` rays (the
    first ``n mod eyes`` eyes one more) toward the ball of radius ``radius``
    about the origin, their directions drawn uniformly by solid angle within
    the cone of directions that meet the ball (``cos`` of the angle to the
    eye's axis uniform in ``[cos a, 1]``, ``sin a = radius / eye_radius``;
    the azimuth uniform).  The distribution of the rays is invariant under
    rotations about the origin up to the discreteness of the eyes: no
    direction is preferred.

    Parameters
    ----------
    n : int
        Number of rays.
    rng : numpy.random.Generator
        Source of the ray directions.
    eyes : int, optional
        Number of eyes (default ``ceil(sqrt(n))``: as many eyes as rays per eye).
    eye_radius, radius : float
        ``0 < radius < eye_radius``.

    Returns
    -------
    RaySamples
        ``origins`` the eyes, ``directions`` unit; ``screen`` the point of each
        ray closest to the origin; ``shape`` ``(1, n)`` (no raster).
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise InvalidInputError(f"n: expected a positive integer, got {n!r}", "n")
    if eyes is None:
        eyes = math.isqrt(int(n) - 1) + 1
    if not (isinstance(eyes, (int, np.integer)) and 1 <= eyes <= n):
        raise InvalidInputError(f"eyes: expected an integer in [1, n = {n}], got {eyes!r}", "eyes")
    if not (math.isfinite(radius) and math.isfinite(eye_radius) and 0 < radius < eye_radius):
        raise InvalidInputError(f"radius: expected 0 < radius < eye_radius, got radius={radius!r}, "
                                f"eye_radius={eye_radius!r}", "radius")
    e = fibonacci_sphere(int(eyes))
    which = np.arange(n) % eyes  # eye of each ray
    axis = -e[which]  # toward the origin
    o = eye_radius * e[which]
    cos_a = math.sqrt(1.0 - (radius / eye_radius) ** 2)
    c = rng.uniform(cos_a, 1.0, n)
    az = rng.uniform(0.0, 2.0 * math.pi, n)
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    # an orthonormal frame (a, b) perpendicular to each axis
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    a = np.cross(axis, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(axis, a)
    d = c[:, None] * axis + s[:, None] * (np.cos(az)[:, None] * a + np.sin(az)[:, None] * b)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    closest = o - np.einsum("ij,ij->i", o, d)[:, None] * d
    return RaySamples(origins=o, directions=d, screen=closest, shape=(1, int(n)))


def rotation_about(axis, degrees: float) -> np.ndarray:
    """(3, 3) rotation by ``degrees`` about ``axis`` ("x", "y", "z" or a 3-vector), right-handed."""
    if isinstance(axis, str):
        if axis not in ("x", "y", "z"):
            raise InvalidInputError(f"axis: expected 'x', 'y', 'z' or a vector, got {axis!r}", "axis")
        axis = np.eye(3)["xyz".index(axis)]
    a = as_array(axis, "axis", (3,))
    a = a / np.linalg.norm(a)
    th = math.radians(degrees)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Parameters
    ----------
    eye : (3,) float
    rotation : (3, 3) float
        Columns: image right, image up, viewing direction (world).
    focal : float
        Distance of the image plane, in units of half the image width.
    width, height : int
        Resolution in pixels.
    supersample : int
        Rays per pixel, a square number (4 = a 2 x 2 grid in each pixel).
    """

    eye: np.ndarray = DEFAULT_EYE
    rotation: np.ndarray = None
    focal: float = DEFAULT_FOCAL
    width: int = 250
    height: int = 250
    supersample: int = DEFAULT_SUPERSAMPLE

    def __post_init__(self):
        object.__setattr__(self, "eye", as_array(self.eye, "eye", (3,)))
        R = np.eye(3) if self.rotation is None else self.rotation
        R = as_array(R, "rotation", (3, 3))
        if np.abs(R).max() > 1 + ORTHONORMAL_TOL or not np.allclose(R.T @ R, np.eye(3), atol=ORTHONORMAL_TOL) or np.linalg.det(R) < 0:
            raise InvalidInputError("rotation: expected a proper rotation matrix (orthonormal, det +1)", "rotation")
        object.__setattr__(self, "rotation", R)
        if not (np.isfinite(self.focal) and self.focal > 0):
            raise InvalidInputError(f"focal: expected a positive number, got {self.focal!r}", "focal")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise InvalidInputError(f"{name}: expected a positive integer, got {v!r}", name)
        s = self.supersample
        if not (isinstance(s, (int, np.integer)) and s >= 1 and math.isqrt(int(s)) ** 2 == s):
            raise InvalidInputError(f"supersample: expected a square number of rays per pixel (1, 4, 9, ...), got {s!r}", "supersample")

    # ---------------------------------------------------------- construction
    @classmethod
    def look_at(cls, eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), **kwargs) -> "Camera":
        """Camera at ``eye`` looking at ``target`` with image up near ``up``."""
        # (bounded like a flat's entries: a view direction that overflows would be
        # taken for one parallel to ``up``)
        eye = as_array(eye, "eye", (3,), max_abs=MAX_ENTRY)
        fwd = as_array(target, "target", (3,), max_abs=MAX_ENTRY) - eye
        if not np.linalg.norm(fwd) > 0:
            raise InvalidInputError("target: must differ from eye", "target")
        fwd /= np.linalg.norm(fwd)
        up = as_array(up, "up", (3,))
        right = np.cross(up, fwd)
        if not np.linalg.norm(right) > 1e-12:
            raise InvalidInputError("up: must not be parallel to the viewing direction", "up")
        right /= np.linalg.norm(right)
        up2 = np.cross(fwd, right)
        return cls(eye=eye, rotation=np.stack([right, up2, fwd], axis=1), **kwargs)

    @classmethod
    def orbit(cls, yaw: float, pitch: float, distance: float = 3.0, **kwargs) -> "Camera":
        """Camera on a sphere around the origin, looking at it.

        ``yaw`` (about +y) and ``pitch`` (about the image's right axis) in
        degrees; (0, 0) is the default camera at (0, 0, -distance).
        """
        R = rotation_about("y", yaw) @ rotation_about("x", pitch)
        return cls(eye=R @ np.array([0.0, 0.0, -distance]), rotation=R, **kwargs)

    def rotated(self, axis, degrees: float) -> "Camera":
        """Eye and image plane turned together about ``axis`` through the origin."""
        R = rotation_about(axis, degrees)
        return replace(self, eye=R @ self.eye, rotation=R @ self.rotation)

    def with_(self, **changes) -> "Camera":
        """A copy with some parameters changed."""
        return replace(self, **changes)

    # ------------------------------------------------------------------ rays
    @property
    def side(self) -> int:
        """Supersamples per pixel side (sqrt of ``supersample``)."""
        return math.isqrt(int(self.supersample))

    @property
    def nrays(self) -> int:
        return self.width * self.height * self.supersample

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays of all supersamples in scanline order over the fine raster.

        Returns
        -------
        origins : (H*s * W*s, 3) float64
            The eye, repeated.
        directions : (H*s * W*s, 3) float64
            Unit directions; row ``i`` is fine pixel ``divmod(i, W*s)``, row 0
            of the image at the top.
        """
        s = self.side
        W, H = self.width * s, self.height * s
        f = float(self.focal)
        u = ((np.arange(W) + 0.5) / W * 2 - 1)
        v = (1 - (np.arange(H) + 0.5) / H * 2) * (self.height / self.width)
        # R orthonormal: |R (u, v, f)| = sqrt(u^2 + v^2 + f^2); separable per row/column
        inv = 1.0 / np.sqrt(v[:, None] ** 2 + (u[None, :] ** 2 + f * f))  # (H, W)
        right, up, fwd = self.rotation.T  # columns of R
        d = np.empty((H, W, 3))
        for c in range(3):
            np.multiply(np.add.outer(v * up[c], u * right[c]) + f * fwd[c], inv, out=d[:, :, c])
        o = np.empty((H * W, 3))
        o[:] = self.eye
        return o, d.reshape(H * W, 3)

    def resolve(self, values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Average supersamples into pixels.

        Parameters
        ----------
        values : (H*s * W*s, C) float
            One row per ray of :meth:`rays`.
        weights : (H*s * W*s,) float, optional
            Per-ray weights (e.g. 0 for rays without a value); pixels whose
            weights sum to zero become NaN.

        Returns
        -------
        (H, W, C) float64
        """
        s = self.side
        values = np.asarray(values, dtype=np.float64)
        C = values.shape[1]
        v = values.reshape(self.height, s, self.width, s, C)
        if weights is None:
            return v.mean(axis=(1, 3))
        w = np.asarray(weights, dtype=np.float64).reshape(self.height, s, self.width, s, 1)
        num = (np.where(w > 0, v, 0.0) * w).sum(axis=(1, 3))
        den = w.sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)

    def to_dict(self) -> dict:
        """JSON-ready description."""
        return {"eye": self.eye.tolist(), "rotation": self.rotation.tolist(), "focal": float(self.focal),
                "width": int(self.width), "height": int(self.height), "supersample": int(self.supersample)}
