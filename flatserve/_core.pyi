"""
flatserve's private native core (CGAL dD Delaunay, AABB ray casting, coordinates of lines). Not a public API: use flatserve.Triangulation and friends. Arrays passed in must be C-contiguous float64, already validated by the Python wrappers.
"""

import enum
from typing import Annotated

import numpy
from numpy.typing import NDArray

import flatserve.errors


# Generated from the built extension by nanobind's stubgen (`make stub`); do not edit.

cgal_version: str

eigen_version: str

class SnapshotError(flatserve.errors.SnapshotError):
    pass

class LocateKind(enum.IntEnum):
    """Where a query point lies in the triangulation."""

    IN_CELL = 0
    """Strictly inside a full cell."""

    ON_FACET = 1
    """On a facet (one weight exactly 0)."""

    ON_FACE = 2
    """On a lower-dimensional face (edge, ...)."""

    ON_VERTEX = 3
    """On a vertex."""

    OUTSIDE_CONVEX_HULL = 4
    """Beyond a hull facet."""

    OUTSIDE_AFFINE_HULL = 5
    """The triangulation does not span R^D yet."""

QUERY_CHUNK: int = 2048

def default_threads() -> int: ...

class Triangulation:
    def __init__(self, ndim: int) -> None: ...

    @property
    def ndim(self) -> int: ...

    @property
    def current_dimension(self) -> int: ...

    @property
    def nvertices(self) -> int: ...

    @property
    def nfullcells(self) -> int: ...

    @property
    def generation(self) -> int:
        """
        Inserts so far: the cells an insert makes carry its number (conflicts(since=...)).
        """

    def nfinite_cells(self) -> int: ...

    def insert(self, points: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], own: Annotated[NDArray[numpy.uint8], dict(shape=(None,), order='C', device='cpu', writable=False)] | None = None) -> tuple[NDArray[numpy.int64], int]:
        """
        Inserts the points (n, D); with own (one byte per vertex), only those that become neighbours of a vertex with own[id] (the others: id -1).
        """

    def locate(self, xi: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], hilbert: bool = True, threads: int = 0) -> tuple[NDArray[numpy.int64], NDArray[numpy.float64], NDArray[numpy.int8], NDArray[numpy.int64]]: ...

    def within(self, xi: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], radius: float, threads: int = 0) -> NDArray[numpy.uint8]:
        """
        Per row of xi, 1 if some vertex lies within radius of it (Euclidean, inclusive), else 0.
        """

    def interpolate(self, xi: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], values: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], clamp: bool = False, hilbert: bool = True, threads: int = 0) -> tuple[NDArray[numpy.float64], NDArray[numpy.bool_]]: ...

    def interpolate_owned(self, xi: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], values: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], own: Annotated[NDArray[numpy.uint8], dict(shape=(None,), order='C', device='cpu', writable=False)], clamp: bool = False, hilbert: bool = True, threads: int = 0) -> tuple[NDArray[numpy.float64], NDArray[numpy.bool_], NDArray[numpy.int64]]:
        """
        interpolate, answering only the queries whose cell has a vertex with own[id]; the others: NaN, not inside, and forward = the id of their cell's lexicographically first finite vertex (-1 when answered).
        """

    def count_cells(self, own: Annotated[NDArray[numpy.uint8], dict(shape=(None,), order='C', device='cpu', writable=False)]) -> int:
        """
        Finite cells whose lexicographically first vertex has own[id] (over Tile & Merge's tiles: each cell of the whole triangulation once).
        """

    def conflicts(self, own: Annotated[NDArray[numpy.uint8], dict(shape=(None,), order='C', device='cpu', writable=False)], lo: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], hi: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], start: Annotated[NDArray[numpy.int64], dict(shape=(None,), order='C', device='cpu', writable=False)], skip: int = -1, seeds: Annotated[NDArray[numpy.int64], dict(shape=(None,), order='C', device='cpu', writable=False)] | None = None, since: int = -1) -> list:
        """
        Tile & Merge's exchange: per group of boxes (lo, hi: (nbox, D); group g is boxes start[g]:start[g+1], its bounding box first), the sorted ids of the vertices of the cells with a vertex with own[id] whose circumscribed ball (half-space beyond the hull facet for an infinite cell) meets one of its boxes; every cell (a search from the boxes' centres), those made by the inserts after generation since (one pass over the cells), or those incident to the seed vertices; group skip untested.
        """

    def points(self) -> NDArray[numpy.float64]: ...

    def simplices(self) -> NDArray[numpy.int64]: ...

    def is_valid(self, verbose: bool = False) -> bool: ...

    def save(self, path: str, values: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)] | None) -> None: ...

    def to_bytes(self, values: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)] | None) -> bytes: ...

    @staticmethod
    def load(path: str) -> tuple[Triangulation, NDArray[numpy.float64] | None]: ...

    @staticmethod
    def from_bytes(data: bytes) -> tuple[Triangulation, NDArray[numpy.float64] | None]: ...

class RayCaster:
    def __init__(self, vertices: Annotated[NDArray[numpy.float64], dict(shape=(None, 3), order='C', device='cpu', writable=False)], faces: Annotated[NDArray[numpy.int64], dict(shape=(None, 3), order='C', device='cpu', writable=False)]) -> None: ...

    @property
    def size(self) -> int: ...

    def cast(self, origins: Annotated[NDArray[numpy.float64], dict(shape=(None, 3), order='C', device='cpu', writable=False)], directions: Annotated[NDArray[numpy.float64], dict(shape=(None, 3), order='C', device='cpu', writable=False)], threads: int = 0) -> tuple[Annotated[NDArray[numpy.float64], dict(shape=(None,))], Annotated[NDArray[numpy.int64], dict(shape=(None,))]]: ...

class CoordinateStatus(enum.IntEnum):
    """Status of one coordinate row (see flatserve.coordinates)."""

    OK = 0

    NOT_REPRESENTABLE = 1

    SINGULAR = 2

    AMBIGUOUS = 3

    NO_SAMPLES = 4

def coordinates_rays3(Qb: Annotated[NDArray[numpy.float64], dict(order='C', device='cpu', writable=False)], rb: Annotated[NDArray[numpy.float64], dict(order='C', device='cpu', writable=False)], origins: Annotated[NDArray[numpy.float64], dict(order='C', device='cpu', writable=False)], directions: Annotated[NDArray[numpy.float64], dict(order='C', device='cpu', writable=False)], roundtrip_tol: float, rcond: float, gap_tol: float, pinv_rcond: float, threads: int = 0) -> tuple[NDArray[numpy.float64], NDArray[numpy.int8], NDArray[numpy.float64]]: ...

def seam_net(cand: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], cand_at: Annotated[NDArray[numpy.int64], dict(shape=(None,), order='C', device='cpu', writable=False)], base: Annotated[NDArray[numpy.float64], dict(shape=(None, None), order='C', device='cpu', writable=False)], base_at: Annotated[NDArray[numpy.int64], dict(shape=(None,), order='C', device='cpu', writable=False)], radius: float, hit: Annotated[NDArray[numpy.uint8], dict(shape=(None,), order='C', device='cpu', writable=False)], threads: int = 0) -> NDArray[numpy.uint8]: ...
