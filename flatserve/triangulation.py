"""Delaunay triangulation of points in R^D with values at the vertices.

:class:`Triangulation` wraps CGAL's dD Delaunay triangulation (``Epick_d``,
static dimensions 2..6, dynamic beyond) in scipy.spatial's vocabulary:
``points``, ``simplices``, ``find_simplex`` (-1 outside), ``barycentric``
(shape (..., D+1)). Queries walk the triangulation from a hint (the previous
answer), in Hilbert order by default, release the GIL and run on several
threads; answers do not depend on the number of threads.

Policies
--------
Sample ids
    Every vertex has a sample id: 0, 1, 2, ... in the order the points were
    first inserted (input row order within a batch). ``points[i]`` and
    ``values[i]`` belong to sample id ``i``.
Duplicates
    Inserting a point equal to an existing vertex (or to an earlier row of the
    same batch) adds no vertex: the row is answered with the existing sample
    id, and its value *replaces* the stored one (the later value wins). The
    count is reported in :class:`InsertResult`.
Outside the convex hull
    ``interpolate(..., outside="nan")`` (default) gives NaN;
    ``outside="clamp"`` gives the value interpolated on the hull facet the walk
    ended at: the query's barycentric coordinates on that facet's hyperplane,
    clamped to >= 0 and renormalised (a cheap, continuous-enough extension, not
    the nearest point of the hull). ``inside`` is False there either way.
Degenerate point sets
    Until the points span R^D (D+1 affinely independent points), every query
    is ``OUTSIDE_AFFINE_HULL``: ids -1, weights NaN, values NaN.
Thread safety
    Queries may run concurrently with each other; :meth:`insert` waits for
    running queries and blocks new ones (readers/writer lock).
"""
from __future__ import annotations

import itertools
import math
import os
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import _native
from ._validate import as_array
from .errors import InvalidInputError
from .options import Order, Outside, choice

__all__ = ["Triangulation", "InsertResult", "Location", "LocateKind", "RWLock", "Held",
           "fresh_state"]


#: Where a query landed (``Location.kind``): an :class:`enum.IntEnum` defined
#: by the extension (``IN_CELL``, ``ON_FACET``, ``ON_FACE``, ``ON_VERTEX``,
#: ``OUTSIDE_CONVEX_HULL``, ``OUTSIDE_AFFINE_HULL``).
LocateKind = _native.LocateKind

#: ``kind <= INSIDE_MAX`` means the query is in the closed convex hull.
INSIDE_MAX = int(LocateKind.ON_VERTEX)



@dataclass(frozen=True)
class InsertResult:
    """Outcome of :meth:`Triangulation.insert`.

    Attributes
    ----------
    ids : ndarray, shape (n,), int64
        Sample id each input row landed on (a new id, or an existing one for a
        duplicate point).
    n_new : int
        Vertices added.
    n_duplicates : int
        Rows that landed on an existing vertex (``n - n_new``, less the rows
        left out by ``neighbours_of``: id -1).
    """

    ids: np.ndarray
    n_new: int
    n_duplicates: int


_STATES = itertools.count(1)


def fresh_state() -> int:
    """A triangulation's state after a change: unique across objects and time, so a
    state never names two contents (:attr:`Held.state`)."""
    return next(_STATES)


@dataclass(frozen=True)
class Held:
    """What a triangulation held when a query was answered, readable by the query's
    ``then`` (:meth:`Triangulation.query`) under the same read lock.

    Attributes
    ----------
    state : int
        Changes with every insert (unique: equal states, equal contents).
    arrays : callable
        ``() -> (points (n, D), values (n, C))``, row = sample id, read only;
        valid while the lock is held (copies or views).
    """

    state: int
    arrays: "Callable[[], tuple[np.ndarray, np.ndarray]]"


@dataclass(frozen=True)
class Location:
    """Answer of :meth:`Triangulation.locate` for q queries.

    Attributes
    ----------
    ids : ndarray, shape (q, D+1), int64
        Sample ids of the vertices of the full cell the walk ended in; -1 for
        the infinite vertex (outside the hull) and everywhere when outside the
        affine hull.
    weights : ndarray, shape (q, D+1), float64
        Barycentric weights over ``ids`` (sum 1). Outside the convex hull: the
        clamped, renormalised weights on the hull facet (0 at the infinite
        vertex); outside the affine hull: NaN.
    kind : ndarray, shape (q,), int8
        :class:`LocateKind` codes.
    simplex : ndarray, shape (q,), int64
        Row of :attr:`Triangulation.simplices` containing the query, -1 outside.
    """

    ids: np.ndarray
    weights: np.ndarray
    kind: np.ndarray
    simplex: np.ndarray

    @property
    def inside(self) -> np.ndarray:
        """(q,) bool: the query lies in the closed convex hull."""
        return self.kind <= INSIDE_MAX


class RWLock:
    """Readers/writer lock (queries share, an insert excludes them), phase-fair.

    A waiting writer keeps new readers out (writers are not starved), and the
    readers waiting when a writer releases the lock get in before the next
    writer (readers are not starved by a writer that inserts slice after slice).
    Not reentrant. ``with lock.read():`` / ``with lock.write():`` hold it.
    """

    def __init__(self):
        self._cond = threading.Condition(threading.Lock())
        self._readers = 0
        self._writer = False
        self._waiting_writers = 0
        self._waiting_readers = 0
        #: readers that waited for a writer enter before the next writer
        self._readers_turn = False

    def acquire_read(self):
        with self._cond:
            self._waiting_readers += 1
            try:
                while self._writer or (self._waiting_writers and not self._readers_turn):
                    self._cond.wait()
            finally:
                self._waiting_readers -= 1
                if not self._waiting_readers and self._readers_turn:
                    self._readers_turn = False
                    self._cond.notify_all()
            self._readers += 1

    def try_acquire_read(self) -> bool:
        """Take the lock as a reader only if that needs no wait (no writer holds or
        awaits it); pair a True with :meth:`release_read`."""
        with self._cond:
            if self._writer or (self._waiting_writers and not self._readers_turn):
                return False
            self._readers += 1
            return True

    def release_read(self):
        with self._cond:
            self._readers -= 1
            if self._readers == 0:
                self._cond.notify_all()

    def acquire_write(self):
        with self._cond:
            self._waiting_writers += 1
            try:
                while self._writer or self._readers or self._readers_turn:
                    self._cond.wait()
            finally:
                self._waiting_writers -= 1
            self._writer = True

    def release_write(self):
        with self._cond:
            self._writer = False
            self._readers_turn = self._waiting_readers > 0
            self._cond.notify_all()

    def read(self) -> "_Reading":
        """Context manager holding the lock as a reader."""
        return _Reading(self)

    def write(self) -> "_Writing":
        """Context manager holding the lock as the writer."""
        return _Writing(self)


class _Reading:
    def __init__(self, lock):
        self._lock = lock

    def __enter__(self):
        self._lock.acquire_read()

    def __exit__(self, *exc):
        self._lock.release_read()


class _Writing(_Reading):
    def __enter__(self):
        self._lock.acquire_write()

    def __exit__(self, *exc):
        self._lock.release_write()


#: Largest accepted ``threads`` argument (more threads than this only cost memory).
MAX_THREADS = 1024
#: largest dimension accepted: a Delaunay triangulation has O(n^ceil(D/2)) cells
#: in the worst case, and even well-spread points give factorially many per vertex
MAX_NDIM = 32


def _threads_arg(threads) -> int:
    if threads is None:
        return 0
    if (isinstance(threads, bool) or not isinstance(threads, (int, np.integer))
            or not 1 <= threads <= MAX_THREADS):
        raise InvalidInputError(
            f"threads: expected an integer in [1, {MAX_THREADS}] or None, got {threads!r}", "threads")
    return int(threads)


class Triangulation:
    """Delaunay triangulation of samples in R^D carrying values.

    Parameters
    ----------
    ndim : int
        Dimension D of the points, 2 <= D <= :data:`MAX_NDIM`. Dimensions 2..6
        use CGAL's static kernels with filtered predicates; higher ones the
        dynamic kernel.

    Examples
    --------
    >>> tri = Triangulation(2)
    >>> res = tri.insert([[0, 0], [1, 0], [0, 1]], values=[[0.0], [1.0], [2.0]])
    >>> values, inside = tri.interpolate([[0.25, 0.25]])
    """

    def __init__(self, ndim: int):
        if (isinstance(ndim, bool) or not isinstance(ndim, (int, np.integer))
                or not 2 <= ndim <= MAX_NDIM):
            raise InvalidInputError(
                f"ndim: expected an integer in [2, {MAX_NDIM}], got {ndim!r}", "ndim")
        self._init(_native.Triangulation(int(ndim)), None)

    def _init(self, core, values):
        self._state = fresh_state()
        self._core = core
        self._ndim = int(core.ndim)
        self._lock = RWLock()
        n = int(core.nvertices)
        self._n = n
        self._points_buf = np.ascontiguousarray(core.points()) if n else np.empty((0, self._ndim))
        if values is None:
            self._values_buf = None
        else:
            self._values_buf = np.ascontiguousarray(values, dtype=np.float64)
        self._simplices = None

    # ------------------------------------------------------------------ access
    @property
    def lock(self) -> RWLock:
        """The readers/writer lock of this triangulation: every reader method holds
        its read side, :meth:`insert` its write side. Hold ``lock.write()`` yourself
        to keep readers out across several calls (never from a reader)."""
        return self._lock

    @property
    def ndim(self) -> int:
        """Dimension D of the points."""
        return self._ndim

    @property
    def npoints(self) -> int:
        """Number of samples (= finite vertices)."""
        return self._n

    @property
    def points(self) -> np.ndarray:
        """(npoints, D) float64, row = sample id (read-only view)."""
        v = self._points_buf[: self._n]
        v.flags.writeable = False
        return v

    @property
    def values(self) -> np.ndarray | None:
        """(npoints, C) float64 sample values, or None if none were given."""
        if self._values_buf is None:
            return None
        v = self._values_buf[: self._n]
        v.flags.writeable = False
        return v

    @property
    def nchannels(self) -> int:
        """Number of value channels C (0 without values)."""
        return 0 if self._values_buf is None else self._values_buf.shape[1]

    @property
    def simplices(self) -> np.ndarray:
        """(nsimplex, D+1) int64: finite full cells as sample ids.

        Row order matches :meth:`find_simplex`; cells are positively oriented.
        """
        with _Reading(self._lock):
            s = self._simplices
            if s is None:
                s = self._core.simplices()
                s.flags.writeable = False
                self._simplices = s
            return s

    @property
    def nsimplex(self) -> int:
        """Number of finite full cells."""
        with _Reading(self._lock):
            if self._simplices is not None:
                return self._simplices.shape[0]
            return int(self._core.nfinite_cells())

    @property
    def current_dimension(self) -> int:
        """Dimension of the affine hull of the points (-1 when empty)."""
        return int(self._core.current_dimension)

    @property
    def generation(self) -> int:
        """Inserts so far (0 for a triangulation just built or loaded): the cells
        an insert makes carry its number, for :meth:`conflicts` ``since``. An
        insert whose every row was left out (``neighbours_of``) changes nothing
        and is not counted."""
        return int(self._core.generation)

    #: One triangulation (a :class:`~flatserve.tiles.TiledTriangulation` has several).
    ntiles = 1

    #: Always: an insert leaves nothing pending (a
    #: :class:`~flatserve.tiles.TiledTriangulation`'s exchange may be).
    settled = True

    def settle(self) -> None:
        """Nothing to do: an insert leaves nothing pending (the
        :class:`~flatserve.tiles.TiledTriangulation` protocol)."""

    def __len__(self) -> int:
        return self._n

    def __repr__(self) -> str:
        return (f"Triangulation(ndim={self._ndim}, npoints={self._n}, "
                f"nchannels={self.nchannels})")

    # ------------------------------------------------------------------ insert
    def insert(self, points, values=None, *, neighbours_of=None) -> InsertResult:
        """Insert a batch of samples.

        Parameters
        ----------
        points : array_like, shape (n, D)
            Finite coordinates.
        values : array_like, shape (n, C) or (n,), optional
            Values at the points (float64; float32 accepted). Required once the
            triangulation has values; C must match earlier batches. A 1-D array
            means C = 1.
        neighbours_of : ndarray of bool or uint8, shape (npoints,), optional
            Insert only the points that become neighbours of a marked vertex
            (Tile & Merge's halo: a tile needs the foreign points in the stars of
            its own vertices); the others are left out, with id -1. A point that
            is no neighbour of a vertex in the triangulation of some points is
            none in that of more points, so a point left out is not needed
            later as long as no vertex is newly marked. Below full dimension
            every point is inserted. A duplicate of a vertex lands on it.

        Returns
        -------
        InsertResult
            Per-row sample ids, number of new vertices and of duplicates (whose
            values replace the stored ones, the later row winning).
        """
        pts = as_array(points, "points", ("n", self._ndim))
        n = pts.shape[0]
        vals = None
        if values is not None:
            v = np.asarray(values)
            if v.ndim == 1:
                v = v.reshape(-1, 1)
            C = self.nchannels if self._values_buf is not None else (v.shape[1] if v.ndim == 2 else None)
            vals = as_array(v, "values", (n, C if C else "C"))
            if self._values_buf is None and self._n > 0:
                raise InvalidInputError(
                    "values: this triangulation was built without values", "values")
        elif self._values_buf is not None:
            raise InvalidInputError(
                f"values: required, shape ({n}, {self.nchannels})", "values")
        near = None
        if neighbours_of is not None:
            near = np.ascontiguousarray(neighbours_of, dtype=np.uint8)
        with _Writing(self._lock):
            if near is not None and near.shape != (self._n,):
                raise InvalidInputError(f"neighbours_of: expected shape ({self._n},), "
                                        f"got {near.shape}", "neighbours_of")
            ids, n_new = self._core.insert(pts, near)
            n_new = int(n_new)
            old = self._n
            new_n = old + n_new
            self._points_buf = _grow(self._points_buf, new_n)
            if vals is not None:
                if self._values_buf is None:
                    self._values_buf = np.empty((0, vals.shape[1]))
                self._values_buf = _grow(self._values_buf, new_n)
            # New ids are old..new_n-1 in input row order.
            fresh = ids >= old
            self._points_buf[ids[fresh]] = pts[fresh]
            kept = ids >= 0
            if vals is not None:
                # later row wins: keep the last occurrence of each id
                rev_ids = ids[::-1]
                uniq, first_in_rev = np.unique(rev_ids, return_index=True)
                held = uniq >= 0  # (rows left out by neighbours_of: -1)
                self._values_buf[uniq[held]] = vals[n - 1 - first_in_rev[held]]
            self._n = new_n
            self._simplices = None
            self._state = fresh_state()
        ids.flags.writeable = False
        return InsertResult(ids=ids, n_new=n_new,
                            n_duplicates=int(kept.sum()) - n_new)

    def _held_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Points and values as they are (read-only views; under a lock)."""
        n = self._n
        p, v = self._points_buf[:n], self._values_buf[:n]
        p.flags.writeable = v.flags.writeable = False
        return p, v

    # ------------------------------------------------------------------ queries
    def _queries(self, xi, name="xi"):
        arr = np.asarray(xi, dtype=np.float64) if not isinstance(xi, np.ndarray) else xi
        if arr.ndim == 0 or arr.shape[-1] != self._ndim:
            raise InvalidInputError(
                f"{name}: expected shape (..., {self._ndim}), got {np.shape(arr)}", name)
        lead = arr.shape[:-1]
        flat = as_array(np.reshape(arr, (-1, self._ndim)), name, (None, self._ndim))
        return flat, lead

    def within(self, xi, radius: float, threads: int | None = None) -> np.ndarray:
        """Whether some sample lies within ``radius`` of each query.

        Every sample is scanned until one is found (no cell is used: the answer
        depends on the samples only, not on how they were inserted).

        Parameters
        ----------
        xi : array_like, shape (..., D)
            Query points.
        radius : float
            Euclidean distance, finite and >= 0 (inclusive).
        threads : int, optional
            Worker threads (default: all cores). Answers do not depend on it.

        Returns
        -------
        ndarray of bool, shape (...,)

        Example
        -------
        >>> import numpy as np, flatserve
        >>> t = flatserve.Triangulation(2)
        >>> _ = t.insert(np.eye(3, 2))
        >>> t.within([[0.9, 0.0], [0.5, 0.5]], 0.2).tolist()
        [True, False]
        """
        q, lead = self._queries(xi)
        r = check_radius(radius)
        th = _threads_arg(threads)
        with _Reading(self._lock):
            hit = self._core.within(q, r, th)
        return hit.astype(bool).reshape(lead)

    def locate(self, xi, order: Order | str = Order.HILBERT, threads: int | None = None) -> Location:
        """Locate queries: containing cell, barycentric weights, kind.

        Parameters
        ----------
        xi : array_like, shape (..., D)
            Query points.
        order : {"hilbert", "given"}
            "hilbert" sorts the batch along a Hilbert curve and starts each
            walk from the previous answer (best for random order); "given"
            keeps the caller's order (e.g. image scanlines) and still chains.
        threads : int, optional
            Worker threads (default: all cores). Answers do not depend on it.

        Returns
        -------
        Location
            Arrays shaped (..., D+1) / (...,).
        """
        q, lead = self._queries(xi)
        order = choice(order, Order, "order")
        th = _threads_arg(threads)
        with _Reading(self._lock):
            ids, w, kind, simplex = self._core.locate(q, order is Order.HILBERT, th)
        D1 = self._ndim + 1
        return Location(ids=ids.reshape(lead + (D1,)), weights=w.reshape(lead + (D1,)),
                        kind=kind.reshape(lead), simplex=simplex.reshape(lead))

    def find_simplex(self, xi, order: Order | str = Order.HILBERT, threads: int | None = None) -> np.ndarray:
        """Row of :attr:`simplices` containing each query, -1 outside (shape (...,))."""
        return self.locate(xi, order=order, threads=threads).simplex

    def barycentric(self, xi, order: Order | str = Order.HILBERT, threads: int | None = None) -> np.ndarray:
        """Barycentric coordinates (..., D+1) in the simplex ``find_simplex(xi)``.

        Weights follow the vertex order of ``simplices[find_simplex(xi)]``;
        NaN rows for queries outside the convex hull.
        """
        loc = self.locate(xi, order=order, threads=threads)
        w = loc.weights.copy()
        w[~loc.inside] = np.nan
        return w

    def interpolate(self, xi, outside: Outside | str = Outside.NAN, order: Order | str = Order.HILBERT,
                    threads: int | None = None, values=None):
        """Piecewise-linear interpolation of the sample values.

        Parameters
        ----------
        xi : array_like, shape (..., D)
            Query points.
        outside : {"nan", "clamp"}
            Policy beyond the convex hull (see module docstring).
        order : {"hilbert", "given"}
            See :meth:`locate`.
        threads : int, optional
            Worker threads (default all cores); results are identical.
        values : array_like, shape (npoints, C), optional
            Interpolate these per-sample values instead of :attr:`values`.

        Returns
        -------
        values : ndarray, shape (..., C), float64
        inside : ndarray, shape (...,), bool
        """
        q, lead = self._queries(xi)
        outside = choice(outside, Outside, "outside")
        order = choice(order, Order, "order")
        th = _threads_arg(threads)
        with _Reading(self._lock):
            if values is None:
                if self._values_buf is None:
                    raise InvalidInputError(
                        "values: the triangulation has no values; pass values=", "values")
                vals = self._values_buf[: self._n]
            else:
                v = np.asarray(values)
                if v.ndim == 1:
                    v = v.reshape(-1, 1)
                vals = as_array(v, "values", (self._n, "C"))
            out, inside = self._core.interpolate(q, vals, outside is Outside.CLAMP, order is Order.HILBERT, th)
        return out.reshape(lead + (vals.shape[1],)), inside.reshape(lead)

    def query(self, xi, outside: Outside | str = Outside.NAN, order: Order | str = Order.HILBERT,
              threads: int | None = None, *, locate: bool = False, blocking: bool = True,
              then=None):
        """:meth:`interpolate` (and with ``locate`` :meth:`locate`) under one read lock,
        so both see the same triangulation.

        Parameters
        ----------
        xi, outside, order, threads
            As for :meth:`interpolate`.
        locate : bool
            Also return the :class:`Location` of the queries.
        blocking : bool
            False: return None at once, instead of waiting, when an insert holds or
            awaits the lock (for callers that must never wait, an event loop).
        then : callable, optional
            ``then(values, inside, location, held) -> values``, run under the same
            read lock (``held``: :class:`Held`): answers made from the samples
            themselves (the gradient interpolant's slopes) see the triangulation
            that answered.

        Returns
        -------
        (values, inside, Location or None), or None (see ``blocking``)
        """
        q, lead = self._queries(xi)
        outside = choice(outside, Outside, "outside")
        order = choice(order, Order, "order")
        th = _threads_arg(threads)
        if self._values_buf is None:
            raise InvalidInputError("values: the triangulation has no values", "values")
        if blocking:
            self._lock.acquire_read()
        elif not self._lock.try_acquire_read():
            return None
        try:
            hilbert = order is Order.HILBERT
            vals = self._values_buf[: self._n]
            out, inside = self._core.interpolate(q, vals, outside is Outside.CLAMP, hilbert, th)
            loc = None
            if locate:
                ids, w, kind, simplex = self._core.locate(q, hilbert, th)
                D1 = self._ndim + 1
                loc = Location(ids=ids.reshape(lead + (D1,)), weights=w.reshape(lead + (D1,)),
                               kind=kind.reshape(lead), simplex=simplex.reshape(lead))
            if then is not None:
                out = then(out, inside, loc, Held(self._state, self._held_arrays))
        finally:
            self._lock.release_read()
        return out.reshape(lead + (vals.shape[1],)), inside.reshape(lead), loc

    # ------------------------------------------------------------ tiles (Tile & Merge)
    def interpolate_owned(self, xi, own, outside: Outside | str = Outside.NAN,
                          order: Order | str = Order.HILBERT, threads: int | None = None):
        """:meth:`interpolate`, answering only from cells with a vertex of ``own``.

        A tile of a triangulation split by Tile & Merge (:mod:`flatserve.tiles`)
        knows the cells around its own vertices exactly, not those around its
        halo only; a query whose cell has no own vertex is handed on.

        Parameters
        ----------
        xi : array_like, shape (n, D)
        own : ndarray, shape (npoints,), bool or uint8
            Per sample id: the vertex is this tile's own.
        outside, order, threads
            As for :meth:`interpolate`.

        Returns
        -------
        values : ndarray, shape (n, C)
            NaN where not answered.
        inside : ndarray, shape (n,), bool
        forward : ndarray, shape (n,), int64
            -1 where answered; else the sample id of the cell's lexicographically
            first finite vertex (whose owner holds the cell exactly, if it is one of
            the whole triangulation's).
        """
        q, _ = self._queries(xi)
        outside = choice(outside, Outside, "outside")
        order = choice(order, Order, "order")
        mask = np.ascontiguousarray(own, dtype=np.uint8)
        if mask.shape != (self._n,):
            raise InvalidInputError(f"own: expected shape ({self._n},), got {mask.shape}", "own")
        if self._values_buf is None:
            raise InvalidInputError("values: the triangulation has no values", "values")
        with _Reading(self._lock):
            return self._core.interpolate_owned(q, self._values_buf[: self._n], mask,
                                                outside is Outside.CLAMP,
                                                order is Order.HILBERT, _threads_arg(threads))

    def count_cells(self, own) -> int:
        """Finite cells whose lexicographically first vertex is in ``own`` (shape
        (npoints,), bool or uint8): over the tiles of :mod:`flatserve.tiles`, each
        cell of the whole triangulation is counted once, by the owner of that vertex."""
        mask = np.ascontiguousarray(own, dtype=np.uint8)
        if mask.shape != (self._n,):
            raise InvalidInputError(f"own: expected shape ({self._n},), got {mask.shape}", "own")
        with _Reading(self._lock):
            return int(self._core.count_cells(mask))

    def conflicts(self, own, lo, hi, start, skip: int = -1, seeds=None,
                  since: int | None = None) -> list[np.ndarray]:
        """Tile & Merge's exchange step: which vertices each group of boxes must receive.

        For every cell with at least one vertex of ``own`` whose circumscribed
        ball (for an infinite cell, the half-space beyond its hull facet) meets
        a box of group ``g``, the ids of the cell's finite vertices. A point of
        another tile inside such a ball would make the cell non-Delaunay; sending
        the cell's vertices to that tile lets it send such points back (Caraffa
        et al., "Tile & Merge", IEEE BigData 2019). Conservative: a ball that
        cannot be computed meets every group.

        Parameters
        ----------
        own : ndarray, shape (npoints,), bool or uint8
        lo, hi : array_like, shape (nbox, D)
            Closed boxes (a tile's own points: their bounding box, then the boxes
            of their parts).
        start : array_like of int, shape (ngroups + 1,)
            Group ``g`` is boxes ``start[g]:start[g+1]``, its bounding box first.
        skip : int
            A group not tested (the tile's own), -1: none.
        seeds : array_like of int, optional
            Scan only the cells incident to these vertices (those an insertion of
            them created), found by a walk around each: for a few vertices.
        since : int, optional
            Scan only the cells made by the inserts after :attr:`generation` was
            ``since`` (the same cells as the seeds of those inserts' new
            vertices), found in one pass over every cell: for many vertices.
            Default (neither): every cell, found by a search from the cells
            holding the boxes' centres through the cells whose ball meets a box
            (they are connected: the cells whose ball holds a point are, and a
            box is convex), so that only those and their neighbours are tested
            (a ball that cannot be computed then meets every group once
            reached); past a third of the cells, or with a box not finite, a
            pass over the cells.

        Returns
        -------
        list of ndarray of int64
            Per group, sorted unique sample ids (empty for ``skip``).
        """
        mask = np.ascontiguousarray(own, dtype=np.uint8)
        if mask.shape != (self._n,):
            raise InvalidInputError(f"own: expected shape ({self._n},), got {mask.shape}", "own")
        lo = as_array(lo, "lo", (None, self._ndim), finite=False)  # an empty box: +-inf
        hi = as_array(hi, "hi", (lo.shape[0], self._ndim), finite=False)
        st = np.ascontiguousarray(start, dtype=np.int64).reshape(-1)
        sd = None if seeds is None else np.ascontiguousarray(seeds, dtype=np.int64).reshape(-1)
        if sd is not None and since is not None:
            raise InvalidInputError("seeds, since: give one of them, not both", "since")
        if since is not None and not 0 <= int(since) <= self.generation:
            raise InvalidInputError(f"since: expected a generation in 0..{self.generation}, "
                                    f"got {since}", "since")
        with _Reading(self._lock):
            return list(self._core.conflicts(mask, lo, hi, st, int(skip), sd,
                                             -1 if since is None else int(since)))

    # ------------------------------------------------------------------ checks
    def is_valid(self, verbose: bool = False) -> bool:
        """Full CGAL validity check (combinatorics, orientation, Delaunay) and ids."""
        with _Reading(self._lock):
            return bool(self._core.is_valid(verbose))

    # ------------------------------------------------------------------ snapshots
    def _values_arg(self):
        return None if self._values_buf is None else self._values_buf[: self._n]

    def save(self, path) -> None:
        """Write a snapshot (points, ids, cells, neighbours, values) to ``path``.

        Written to a temporary file beside ``path`` then renamed (atomic).

        Raises
        ------
        flatserve.errors.SnapshotError
            The file cannot be written (the temporary file is removed).
        """
        path = os.fspath(path)
        tmp = f"{path}.tmp-{os.getpid()}-{threading.get_ident()}"
        with _Reading(self._lock):
            try:
                self._core.save(tmp, self._values_arg())
                os.replace(tmp, path)
            except BaseException:
                _unlink_quietly(tmp)
                raise

    def to_bytes(self) -> bytes:
        """The snapshot as bytes (same format as :meth:`save`).

        Raises
        ------
        flatserve.errors.SnapshotError
            The triangulation is too large for the snapshot format.
        """
        with _Reading(self._lock):
            return self._core.to_bytes(self._values_arg())

    @classmethod
    def load(cls, path) -> "Triangulation":
        """Read a snapshot written by :meth:`save` (no geometric recomputation).

        Raises
        ------
        flatserve.errors.SnapshotError
            Missing, truncated or corrupted file, or another format version
            (raised by the extension as a subclass).
        """
        core, values = _native.Triangulation.load(os.fspath(path))
        return cls._from_core(core, values)

    @classmethod
    def from_bytes(cls, data) -> "Triangulation":
        """Inverse of :meth:`to_bytes`.

        Raises
        ------
        flatserve.errors.SnapshotError
            Truncated or corrupted bytes, or another format version.
        """
        core, values = _native.Triangulation.from_bytes(bytes(data))
        return cls._from_core(core, values)

    @classmethod
    def _from_core(cls, core, values) -> "Triangulation":
        self = cls.__new__(cls)
        self._init(core, values)
        return self


def check_radius(radius, name: str = "radius") -> float:
    """``radius`` as a float: a finite real number >= 0, else InvalidInputError."""
    try:
        r = float(radius) if isinstance(radius, (int, float, np.integer, np.floating)) \
            and not isinstance(radius, (bool, np.bool_)) else math.nan
    except OverflowError:
        r = math.inf
    if not math.isfinite(r) or r < 0:
        raise InvalidInputError(f"{name}: expected a finite distance >= 0, got {radius!r}", name)
    return r


def _positions(at, name: str, n: int) -> np.ndarray:
    """``at`` as an (n,) int64 array of increasing positions, else InvalidInputError."""
    a = np.asarray(at)
    if a.size == 0:
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu" or a.shape != (n,):
        raise InvalidInputError(f"{name}: expected ({n},) integer positions, got "
                                f"{a.dtype} {a.shape}", name)
    if a.dtype.kind == "u" and a.size and a.max() > np.iinfo(np.int64).max:
        raise InvalidInputError(f"{name}: positions beyond int64", name)
    a = np.ascontiguousarray(a, dtype=np.int64)
    if (np.diff(a) <= 0).any():
        raise InvalidInputError(f"{name}: expected increasing positions", name)
    return a


def seam_net(cand, cand_at, base, base_at, radius: float, hit=None,
             threads: int | None = None) -> np.ndarray:
    """Which points of a stream lie farther than ``radius`` from every point before them.

    Candidate ``i`` comes at position ``cand_at[i]``, base point ``j`` at
    ``base_at[j]`` (both increasing; a base point at the same position as a
    candidate comes after it). Candidate ``i`` is kept unless ``hit[i]`` (it
    is known to be near an earlier point, e.g. :meth:`Triangulation.within` of
    the points before the stream), a base point before it or a kept candidate
    before it lies within ``radius`` (Euclidean, inclusive, summed as
    :meth:`Triangulation.within` sums it): the kept candidates are a net of
    the candidates that the base does not already cover, decided in order, so
    a stream cut anywhere into pieces (each piece's base and kept candidates
    joining the points before the next) keeps the same candidates.

    Parameters
    ----------
    cand : (m, D) array_like
    cand_at : (m,) int64 array_like
    base : (b, D) array_like
    base_at : (b,) int64 array_like
    radius : float
    hit : (m,) bool ndarray, optional
    threads : int, optional

    Returns
    -------
    keep : (m,) bool

    Example
    -------
    >>> import numpy as np
    >>> from flatserve.triangulation import seam_net
    >>> x = np.array([[0.0], [0.5], [2.0], [2.1]])
    >>> seam_net(x, [0, 2, 3, 5], np.array([[1.9]]), [4], 1.0).tolist()
    [True, False, True, False]
    """
    c = as_array(cand, "cand", (None, None))
    m, D = c.shape
    b = as_array(base, "base", (None, D)) if np.size(base) else np.empty((0, D))
    ca = _positions(cand_at, "cand_at", m)
    ba = _positions(base_at, "base_at", b.shape[0])
    h = np.zeros(m, np.bool_) if hit is None else np.asarray(hit)
    if h.dtype != np.bool_ or h.shape != (m,):
        raise InvalidInputError(f"hit: expected ({m},) bool, got {h.dtype} {h.shape}", "hit")
    h = np.ascontiguousarray(h.view(np.uint8))
    keep = _native.seam_net(c, ca, np.ascontiguousarray(b, dtype=np.float64), ba,
                            check_radius(radius), h, _threads_arg(threads))
    return keep.astype(bool)


def _grow(buf: np.ndarray, n: int) -> np.ndarray:
    """Return a buffer with at least n rows, keeping the content (amortised doubling)."""
    if buf.shape[0] >= n:
        return buf
    cap = max(n, 2 * buf.shape[0], 16)
    new = np.empty((cap,) + buf.shape[1:], dtype=buf.dtype)
    new[: buf.shape[0]] = buf
    return new


def _unlink_quietly(path):
    try:
        os.unlink(path)
    except OSError:
        pass
