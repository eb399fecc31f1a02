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
    "PinholeCamera",
    "resolve_supersamples",
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
    "RIGID_TOL",
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
#: How far from a rigid transform a pose read from a file may be (rotation
#: part from orthonormal, last row from (0, 0, 0, 1), a quaternion's norm from
#: 1): poses written in single precision or rounded to a few digits pass, and
#: are then projected onto the nearest rotation.
RIGID_TOL = 1e-4
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


def _check_rotation(R, name: str) -> np.ndarray:
    """``R`` as a (3, 3) float64 proper rotation (orthonormal within
    :data:`ORTHONORMAL_TOL`, det +1), else :class:`InvalidInputError` naming ``name``."""
    R = as_array(R, name, (3, 3))
    if (np.abs(R).max() > 1 + ORTHONORMAL_TOL or not np.allclose(R.T @ R, np.eye(3), atol=ORTHONORMAL_TOL)
            or np.linalg.det(R) < 0):
        raise InvalidInputError(f"{name}: expected a proper rotation matrix (orthonormal, det +1)", name)
    return R


def _check_raster(width, height, supersample) -> None:
    """Positive integer ``width`` and ``height``; ``supersample`` a square number."""
    for name, v in (("width", width), ("height", height)):
        if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
            raise InvalidInputError(f"{name}: expected a positive integer, got {v!r}", name)
    s = supersample
    if not (isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 1
            and math.isqrt(int(s)) ** 2 == s):
        raise InvalidInputError(f"supersample: expected a square number of rays per pixel (1, 4, 9, ...), got {s!r}",
                                "supersample")


def resolve_supersamples(values, width: int, height: int, side: int, weights=None) -> np.ndarray:
    """Average the supersamples of a ``height`` x ``width`` image into pixels.

    The rays are in scanline order over the fine raster of ``height * side``
    rows and ``width * side`` columns (:meth:`Camera.rays`,
    :meth:`PinholeCamera.rays`); pixel ``(i, j)`` averages the ``side`` x
    ``side`` block of fine pixels ``(i*side + a, j*side + b)``.

    Parameters
    ----------
    values : (height*side * width*side, C) float
        One row per ray.
    width, height : int
        Image size in pixels.
    side : int
        Supersamples per pixel side.
    weights : (height*side * width*side,) float, optional
        Per-ray weights (e.g. 0 for rays without a value); pixels whose
        weights sum to zero become NaN.

    Returns
    -------
    (height, width, C) float64

    Examples
    --------
    >>> resolve_supersamples(np.arange(4.0)[:, None], 1, 1, 2)[0, 0]
    array([1.5])
    """
    s = side
    values = np.asarray(values, dtype=np.float64)
    C = values.shape[1]
    v = values.reshape(height, s, width, s, C)
    if weights is None:
        return v.mean(axis=(1, 3))
    w = np.asarray(weights, dtype=np.float64).reshape(height, s, width, s, 1)
    num = (np.where(w > 0, v, 0.0) * w).sum(axis=(1, 3))
    den = w.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


class _Raster:
    """What a camera's raster of supersamples gives both kinds of camera: ``width``,
    ``height`` and ``supersample`` (rays per pixel, a square number) are the
    subclass's fields."""

    @property
    def side(self) -> int:
        """Supersamples per pixel side (sqrt of ``supersample``)."""
        return math.isqrt(int(self.supersample))

    @property
    def nrays(self) -> int:
        """Rays of :meth:`rays`: ``width * height * supersample``."""
        return self.width * self.height * self.supersample

    def resolve(self, values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Average supersamples into pixels (:func:`resolve_supersamples`).

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
        return resolve_supersamples(values, self.width, self.height, self.side, weights)


@dataclass(frozen=True)
class Camera(_Raster):
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
        object.__setattr__(self, "rotation", _check_rotation(R, "rotation"))
        if not (np.isfinite(self.focal) and self.focal > 0):
            raise InvalidInputError(f"focal: expected a positive number, got {self.focal!r}", "focal")
        _check_raster(self.width, self.height, self.supersample)

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

    def to_dict(self) -> dict:
        """JSON-ready description."""
        return {"eye": self.eye.tolist(), "rotation": self.rotation.tolist(), "focal": float(self.focal),
                "width": int(self.width), "height": int(self.height), "supersample": int(self.supersample)}


def _positive(value, name: str) -> float:
    """``value`` as a finite positive float, else :class:`InvalidInputError` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{name}: expected a positive number, got {value!r}", name)
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InvalidInputError(f"{name}: expected a positive number, got {value!r}", name)
    return v


def _finite(value, name: str) -> float:
    """``value`` as a finite float, else :class:`InvalidInputError` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{name}: expected a finite number, got {value!r}", name)
    v = float(value)
    if not math.isfinite(v):
        raise InvalidInputError(f"{name}: expected a finite number, got {value!r}", name)
    return v


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (polar decomposition)."""
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion ``q = (w, x, y, z)`` (COLMAP's ``qvec2rotmat``)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _matrix_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)``, ``w >= 0``, of the rotation ``R``.

    Shepperd's method: the largest of ``4w^2, 4x^2, 4y^2, 4z^2`` (read off the
    trace and the diagonal) is divided into the others, so no square root of a
    small number is taken.
    """
    t = np.trace(R)
    cands = np.array([t, R[0, 0], R[1, 1], R[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        r = math.sqrt(1.0 + t) * 2  # 4w
        q = np.array([r / 4, (R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r, (R[1, 0] - R[0, 1]) / r])
    elif k == 1:
        r = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2  # 4x
        q = np.array([(R[2, 1] - R[1, 2]) / r, r / 4, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r])
    elif k == 2:
        r = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2  # 4y
        q = np.array([(R[0, 2] - R[2, 0]) / r, (R[0, 1] + R[1, 0]) / r, r / 4, (R[1, 2] + R[2, 1]) / r])
    else:
        r = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2  # 4z
        q = np.array([(R[1, 0] - R[0, 1]) / r, (R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, r / 4])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


#: NeRF's camera axes (x right, y up, looking down -z) from OpenCV's (x right,
#: y down, looking down +z): negate the second and third columns.
_GL_FROM_CV = np.array([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class PinholeCamera(_Raster):
    """A real camera: a pinhole with intrinsics in pixels (OpenCV's convention).

    Conventions: ``rotation`` maps camera to world coordinates; its columns
    are, in world coordinates, image right (+x, the pixel column ``i``
    grows), image down (+y, the pixel row ``j`` grows) and forward (the
    viewing direction, +z). Image position ``(x, y)`` (in pixels, from the
    top-left corner of the image) looks along ``rotation @ ((x - cx) / fx,
    (y - cy) / fy, 1)``; pixel ``(i, j)`` (column, row) covers ``[i, i+1) x
    [j, j+1)`` and has its centre at ``(i + 1/2, j + 1/2)``, as in COLMAP and
    NeRF. These are COLMAP's camera axes; NeRF's ``transform_matrix`` uses
    OpenGL's (y up, looking down -z) and is converted by :meth:`from_nerf` and
    :meth:`to_nerf`.

    Parameters
    ----------
    eye : (3,) float
        Centre of projection, world coordinates.
    rotation : (3, 3) float
        Camera to world; a proper rotation (orthonormal within
        :data:`ORTHONORMAL_TOL`, det +1).
    fx, fy : float
        Focal lengths in pixels (> 0).
    cx, cy : float
        Principal point in pixels (from the top-left corner of the image).
    width, height : int
        Resolution in pixels.
    supersample : int
        Rays per pixel, a square number (4 = a 2 x 2 grid in each pixel).

    Examples
    --------
    >>> cam = PinholeCamera(eye=(0, 0, -3), rotation=np.eye(3), fx=100, fy=100, cx=32, cy=24,
    ...                     width=64, height=48)
    >>> origins, directions = cam.rays()
    >>> directions.shape
    (3072, 3)
    >>> back = PinholeCamera.from_nerf(**cam.to_nerf_arguments())
    >>> bool(np.allclose(back.rays()[1], directions, atol=1e-12))
    True
    """

    eye: np.ndarray
    rotation: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    supersample: int = 1

    def __post_init__(self):
        object.__setattr__(self, "eye", as_array(self.eye, "eye", (3,)))
        object.__setattr__(self, "rotation", _check_rotation(self.rotation, "rotation"))
        for name in ("fx", "fy"):
            object.__setattr__(self, name, _positive(getattr(self, name), name))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _finite(getattr(self, name), name))
        _check_raster(self.width, self.height, self.supersample)
        for name in ("width", "height", "supersample"):
            object.__setattr__(self, name, int(getattr(self, name)))

    # ---------------------------------------------------------- construction
    @classmethod
    def from_nerf(cls, transform_matrix, *, width: int, height: int, camera_angle_x: float | None = None,
                  fl_x: float | None = None, fl_y: float | None = None, cx: float | None = None,
                  cy: float | None = None, supersample: int = 1, rigid_tol: float = RIGID_TOL) -> "PinholeCamera":
        """A camera from a NeRF / instant-ngp frame.

        Parameters
        ----------
        transform_matrix : (4, 4) or (3, 4) float
            Camera to world in OpenGL's camera axes (x right, y up, looking
            down -z). A rigid transform within ``rigid_tol`` (last row
            (0, 0, 0, 1), rotation part orthonormal, det +1); the rotation part
            is projected onto the nearest rotation.
        width, height : int
            Image size in pixels (``w``, ``h``).
        camera_angle_x : float, optional
            Horizontal field of view in radians: ``fx = width / 2 / tan(camera_angle_x / 2)``.
        fl_x, fl_y : float, optional
            Focal lengths in pixels; ``fl_x`` takes precedence over
            ``camera_angle_x`` (one of the two is needed); ``fl_y`` defaults to
            ``fx``.
        cx, cy : float, optional
            Principal point in pixels; default the image centre.
        supersample : int
            Rays per pixel.
        rigid_tol : float
            Tolerance of the rigidity checks (:data:`RIGID_TOL`).

        Returns
        -------
        PinholeCamera

        Raises
        ------
        InvalidInputError
            Naming ``transform_matrix`` (and how far from rigid it is),
            ``camera_angle_x`` (no focal length given) or the bad intrinsic.
        """
        _check_raster(width, height, supersample)
        M = as_array(transform_matrix, "transform_matrix", (None, 4))
        if M.shape[0] not in (3, 4):
            raise InvalidInputError(f"transform_matrix: expected shape (4, 4) or (3, 4), got {M.shape}",
                                    "transform_matrix")
        if M.shape[0] == 4:
            off = float(np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max())
            if off > rigid_tol:
                raise InvalidInputError(f"transform_matrix: not a rigid transform (last row {M[3].tolist()}, "
                                        f"off (0, 0, 0, 1) by {off:.3g} > {rigid_tol:g})", "transform_matrix")
        R = _rigid_rotation(M[:3, :3], "transform_matrix", rigid_tol)
        if fl_x is not None:
            fx = _positive(fl_x, "fl_x")
        elif camera_angle_x is not None:
            angle = _positive(camera_angle_x, "camera_angle_x")
            if not angle < math.pi:
                raise InvalidInputError(f"camera_angle_x: expected a field of view in (0, pi) radians, "
                                        f"got {camera_angle_x!r}", "camera_angle_x")
            fx = 0.5 * width / math.tan(angle / 2)
        else:
            raise InvalidInputError("camera_angle_x: no focal length (give camera_angle_x or fl_x)",
                                    "camera_angle_x")
        fy = fx if fl_y is None else _positive(fl_y, "fl_y")
        return cls(eye=M[:3, 3], rotation=R * _GL_FROM_CV, fx=fx, fy=fy,
                   cx=width / 2 if cx is None else cx, cy=height / 2 if cy is None else cy,
                   width=width, height=height, supersample=supersample)

    @classmethod
    def look_at(cls, eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), **kwargs) -> "PinholeCamera":
        """Camera at ``eye`` looking at ``target``, the top of its image toward ``up``.

        ``kwargs`` are the other fields (``fx``, ``fy``, ``cx``, ``cy``,
        ``width``, ``height``, ``supersample``).
        """
        eye = as_array(eye, "eye", (3,), max_abs=MAX_ENTRY)
        fwd = as_array(target, "target", (3,), max_abs=MAX_ENTRY) - eye
        if not np.linalg.norm(fwd) > 0:
            raise InvalidInputError("target: must differ from eye", "target")
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, as_array(up, "up", (3,)))
        if not np.linalg.norm(right) > 1e-12:
            raise InvalidInputError("up: must not be parallel to the viewing direction", "up")
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        return cls(eye=eye, rotation=np.stack([right, down, fwd], axis=1), **kwargs)

    @classmethod
    def from_colmap(cls, qvec, tvec, *, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                    supersample: int = 1, rigid_tol: float = RIGID_TOL) -> "PinholeCamera":
        """A camera from a COLMAP image (world to camera) and a pinhole camera.

        Parameters
        ----------
        qvec : (4,) float
            ``(qw, qx, qy, qz)``, the rotation ``R`` of world to camera
            coordinates, ``x_cam = R x_world + t``; its norm within
            ``rigid_tol`` of 1 (it is normalised).
        tvec : (3,) float
            ``t``.
        width, height : int
            Image size in pixels.
        fx, fy, cx, cy : float
            PINHOLE parameters in pixels.
        supersample : int
            Rays per pixel.
        rigid_tol : float
            Tolerance of the quaternion's norm (:data:`RIGID_TOL`).

        Returns
        -------
        PinholeCamera
            ``eye = -R^T t``, ``rotation = R^T``.
        """
        q = as_array(qvec, "qvec", (4,))
        t = as_array(tvec, "tvec", (3,))
        norm = float(np.linalg.norm(q))
        if not abs(norm - 1.0) <= rigid_tol:
            raise InvalidInputError(f"qvec: expected a unit quaternion, its norm {norm:.6g} is off 1 by "
                                    f"{abs(norm - 1.0):.3g} > {rigid_tol:g}", "qvec")
        R = _quaternion_matrix(q / norm)
        return cls(eye=-R.T @ t, rotation=R.T.copy(), fx=fx, fy=fy, cx=cx, cy=cy,
                   width=width, height=height, supersample=supersample)

    def to_nerf(self) -> dict:
        """NeRF / instant-ngp description (:meth:`from_nerf` reads it back).

        Returns
        -------
        dict
            ``transform_matrix`` (4 x 4 nested list, camera to world, OpenGL
            axes), ``fl_x``, ``fl_y``, ``cx``, ``cy`` (pixels), ``w``, ``h``.
        """
        M = np.eye(4)
        M[:3, :3] = self.rotation * _GL_FROM_CV
        M[:3, 3] = self.eye
        return {"transform_matrix": M.tolist(), "fl_x": self.fx, "fl_y": self.fy, "cx": self.cx,
                "cy": self.cy, "w": self.width, "h": self.height}

    def to_nerf_arguments(self) -> dict:
        """Keyword arguments of :meth:`from_nerf` giving this camera back."""
        d = self.to_nerf()
        return {"transform_matrix": d["transform_matrix"], "width": d["w"], "height": d["h"],
                "fl_x": d["fl_x"], "fl_y": d["fl_y"], "cx": d["cx"], "cy": d["cy"],
                "supersample": self.supersample}

    def to_colmap(self) -> dict:
        """COLMAP description (:meth:`from_colmap` reads it back).

        Returns
        -------
        dict
            ``qvec`` ``(qw, qx, qy, qz)`` with ``qw >= 0`` and ``tvec`` (lists,
            world to camera), PINHOLE ``fx``, ``fy``, ``cx``, ``cy``, and
            ``width``, ``height``.
        """
        R = self.rotation.T
        return {"qvec": _matrix_quaternion(R).tolist(), "tvec": (-R @ self.eye).tolist(),
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same pose and field of view at another resolution.

        ``fx`` and ``cx`` scale by ``width / self.width``, ``fy`` and ``cy`` by
        ``height / self.height``.
        """
        _check_raster(width, height, self.supersample)
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, cx=self.cx * sx, fy=self.fy * sy, cy=self.cy * sy,
                       width=int(width), height=int(height))

    def with_(self, **changes) -> "PinholeCamera":
        """A copy with some parameters changed."""
        return replace(self, **changes)

    # ------------------------------------------------------------------ rays
    def grid_rays(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Rays through a grid of image positions, in scanline order.

        Parameters
        ----------
        x : (m,) float
            Image positions along a row, in pixels (pixel column ``i`` has its
            centre at ``i + 1/2``).
        y : (n,) float
            Image positions down a column (pixel row ``j`` at ``j + 1/2``).

        Returns
        -------
        origins : (n*m, 3) float64
            The eye, repeated.
        directions : (n*m, 3) float64
            Unit directions; row ``k`` looks through ``(x[k % m], y[k // m])``.

        Examples
        --------
        >>> cam = PinholeCamera(eye=(0, 0, 0), rotation=np.eye(3), fx=2, fy=2, cx=2, cy=2,
        ...                     width=4, height=4)
        >>> cam.grid_rays([2.0], [2.0])[1]
        array([[0., 0., 1.]])
        """
        x = as_array(x, "x", (None,))
        y = as_array(y, "y", (None,))
        u = (x - self.cx) / self.fx
        v = (y - self.cy) / self.fy
        # R orthonormal: |R (u, v, 1)| = sqrt(u^2 + v^2 + 1); separable per row/column
        inv = 1.0 / np.sqrt(v[:, None] ** 2 + (u[None, :] ** 2 + 1.0))  # (n, m)
        right, down, fwd = self.rotation.T  # columns of R
        d = np.empty((y.size, x.size, 3))
        for c in range(3):
            np.multiply(np.add.outer(v * down[c], u * right[c]) + fwd[c], inv, out=d[:, :, c])
        o = np.empty((y.size * x.size, 3))
        o[:] = self.eye
        return o, d.reshape(-1, 3)

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays of all supersamples in scanline order over the fine raster.

        Fine pixel ``(a, b)`` of pixel ``(i, j)`` (column, row) looks through
        image position ``(i + (a + 1/2) / s, j + (b + 1/2) / s)``, ``s`` the
        :attr:`side`.

        Returns
        -------
        origins : (H*s * W*s, 3) float64
            The eye, repeated.
        directions : (H*s * W*s, 3) float64
            Unit directions; row ``k`` is fine pixel ``divmod(k, W*s)`` (row,
            column), row 0 of the image at the top.
        """
        s = self.side
        return self.grid_rays((np.arange(self.width * s) + 0.5) / s, (np.arange(self.height * s) + 0.5) / s)

    def to_dict(self) -> dict:
        """JSON-ready description (the constructor's arguments)."""
        return {"eye": self.eye.tolist(), "rotation": self.rotation.tolist(), "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height,
                "supersample": self.supersample}


def _rigid_rotation(M: np.ndarray, name: str, tol: float) -> np.ndarray:
    """The rotation nearest to the (3, 3) ``M``, if ``M`` is one within ``tol``.

    Raises
    ------
    InvalidInputError
        Naming ``name`` and how far ``M^T M`` is from the identity, or the
        sign of the determinant.
    """
    off = float(np.abs(M.T @ M - np.eye(3)).max())
    if off > tol:
        raise InvalidInputError(f"{name}: not a rigid transform (rotation part not orthonormal: "
                                f"|R^T R - I| = {off:.3g} > {tol:g}; scaled or sheared?)", name)
    det = float(np.linalg.det(M))
    if det < 0:
        raise InvalidInputError(f"{name}: not a rigid transform (rotation part is a reflection, det {det:.3g})",
                                name)
    return _nearest_rotation(M)
