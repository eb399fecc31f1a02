"""One Delaunay triangulation over tiles: Tile & Merge.

A chart's points are split into tiles, boxes of equal counts cut at the
medians of the axis of the widest interquartile range (a k-d tree:
:class:`Tiling`). Each tile holds a Delaunay triangulation of its own points
and of the foreign points it needs (its halo), found by exchange rounds until
the star of every one of its own vertices is exact, that is the star the vertex
has in the triangulation of all the points (Caraffa, Memari, Yirci, Brédif, "Tile & Merge: distributed Delaunay
triangulations for cloud computing", IEEE BigData 2019; the proof of
consistency in ISPRS Annals 2020):

* a tile sends to another tile the vertices of every cell that has one of its
  own vertices and whose circumscribed ball (the half-space beyond the hull
  facet, for an infinite cell) meets the bounding box of the other tile's own
  points (:meth:`flatserve.Triangulation.conflicts`); a point of that tile
  inside the ball is then a vertex of one of the receiver's cells with such a
  ball, and goes back the other way in the next round;
* a round inserts, of what was received, the points that become neighbours
  of an own vertex (a point that is no neighbour of an own vertex in the
  triangulation of some points is none in that of all of them: it is left
  out, :meth:`flatserve.Triangulation.insert`'s ``neighbours_of``, and not
  sent to that tile again in this exchange); new cells are all incident to a
  new vertex, so the next round scans only those; no new point: done.

The halo a tile holds is therefore close to the least (the foreign vertices of
its own vertices' stars: :meth:`TiledTriangulation.star_halo`), and a point
left out costs its conflict zone, not a place in the triangulation (at 200k
rays of Fig. 11 in 2 tiles: 26.8k points held of 34.7k sent, 22.3k least).
When every cell must be scanned (a new tiling, or a box that grew), the cells
whose ball meets another tile's box are found by a search from the box
(:meth:`flatserve.Triangulation.conflicts`), not by a pass over every cell.

An insert puts its points in their tiles at once and leaves the exchange
pending (:attr:`TiledTriangulation.settled` is then False); the exchange runs
once for every insert since the last (:meth:`TiledTriangulation.settle`), before
anything reads the tiles (a query, a snapshot, the cell count). Inserts in a
row therefore share one exchange: its scan tests the cells the inserts left,
not every cell each of them made and the next one destroyed (at 1M rays of
Fig. 11 in batches of 100k, 4 times fewer cells), and the halo is chosen from
the triangulations as they end up, not grown batch by batch.

A query goes to the tile whose box of the :class:`Tiling` holds it and is
answered there from its cell when the cell has an own vertex of the tile (the
cell is then one of the whole triangulation's); otherwise it is handed on to
the owner of the cell's lexicographically first vertex
(:meth:`flatserve.Triangulation.interpolate_owned`). The extension computes
weights and values with the cell's vertices in lexicographic order of their
points, so a tile answers the bits of the unsplit triangulation: the same
cell, the same weights, the same value (tested against it).

Sample ids are global: 0, 1, ... in the order points were first inserted, as
:class:`flatserve.Triangulation` numbers them; a duplicate point lands on its
existing id and its value replaces the stored one, in every tile that holds it.

Examples
--------
>>> import numpy as np
>>> from flatserve.tiles import TiledTriangulation
>>> rng = np.random.default_rng(0)
>>> pts = rng.random((2000, 3))
>>> tt = TiledTriangulation(3, tiles=4)
>>> res = tt.insert(pts, values=pts[:, :1])
>>> v, inside = tt.interpolate(rng.random((5, 3)) * 0.8 + 0.1)
>>> bool(np.allclose(v[:, 0], v[:, 0]))
True
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np

from ._fieldbase import part_key, read_part
from ._validate import as_array
from .errors import InvalidInputError
from .options import Order, Outside, choice
from .parallel import shard_pool
from .triangulation import (Held, InsertResult, LocateKind, Location, RWLock, Triangulation,
                            check_radius, fresh_state)

__all__ = ["Tiling", "TiledTriangulation", "TileStats", "Tile", "TileHost", "hosting",
           "RETILE_SHARE", "spread", "AUTO_MIN_SAMPLES", "AUTO_MAX_TILES", "auto_tiles",
           "tile_setting"]

#: a tile holding more than this times its share of the points is re-tiled
#: (once the points have doubled since the last cut)
RETILE_SHARE = 1.5
#: a tile's box (around its own points) that must grow grows by this share of
#: its extent beyond the new points, so that the next batches rarely grow it
#: again (each growth costs a scan of every cell of every tile); never beyond the
#: tile's cell of the partition (embedded coordinates are heavy-tailed: 5% of an
#: extent set by an outlier would reach over the other tiles)
SLACK = 0.05
#: the exchange finds the cells an insert made by one pass over a tile's cells
#: (each stamped with its insert) once the new vertices are more than this share
#: of the tile's; fewer, by a walk around each new vertex (measured on 200k 4-D
#: points, benchmarks/bench_tiles.py ``--scan``: the two even at 0.5 %, the pass
#: 1.2x the walk's speed at 1 %, 2.9x at 10 %)
SCAN_SHARE = 0.005
#: ``tiles="auto"``: a chart stays one tile below this many samples, and from
#: there on gets one tile per thread of the shard pool, with at least half this
#: many samples in each. Measured on the Fig. 11 field, 2 tiles on 2 cores
#: against one tile (``benchmarks/bench_tiles.py --sizes``, docs/scaling.md):
#: 1.28x faster at 22.5k rays, 1.43x at 100k, 1.50x at 200k; below, a build
#: takes about a second either way, and the halo (a quarter of the own points
#: and more) is memory for little time
AUTO_MIN_SAMPLES = 20_000
#: ``tiles="auto"`` gives at most this many tiles: the halo grows with the tiles
#: (at 1M rays of Fig. 11: 9 % of the own points for 2 tiles, 22 % for 4, 42 %
#: for 8, and the points sent 11, 32 and 70 %), and only 2 tiles on 2 cores
#: could be timed here
AUTO_MAX_TILES = 4


def tile_setting(tiles) -> int | str:
    """``tiles`` checked: an integer >= 1, or ``"auto"`` (:func:`auto_tiles`).

    Raises
    ------
    InvalidInputError
        Anything else, naming ``tiles``.
    """
    if isinstance(tiles, str) and tiles == "auto":
        return "auto"
    if isinstance(tiles, bool) or not isinstance(tiles, (int, np.integer)) or tiles < 1:
        raise InvalidInputError(f"tiles: expected an integer >= 1 or 'auto', got {tiles!r}",
                                "tiles")
    return int(tiles)


def auto_tiles(nsamples: int, threads: int | None = None) -> int:
    """The tile count ``tiles="auto"`` gives a chart of ``nsamples`` samples.

    One tile below :data:`AUTO_MIN_SAMPLES`; from there on one per thread of the
    shard pool (``threads``, default its size), at most one per
    ``AUTO_MIN_SAMPLES / 2`` samples and at most :data:`AUTO_MAX_TILES`: tiles on
    the cores at once build faster, more tiles than cores only add halo.

    Examples
    --------
    >>> [auto_tiles(n, threads=8) for n in (19_999, 20_000, 35_000, 10**7)]
    [1, 2, 3, 4]
    """
    threads = shard_pool().threads if threads is None else int(threads)
    if nsamples < AUTO_MIN_SAMPLES:
        return 1
    return max(1, min(threads, AUTO_MAX_TILES, nsamples // (AUTO_MIN_SAMPLES // 2)))


def spread(points: np.ndarray) -> np.ndarray:
    """Per axis, the width of the middle half of ``points`` (n, D): the interquartile
    range, or where every one is 0 (half the points or more coincide on each axis),
    the extent. The axis a :class:`Tiling` cuts: embedded coordinates are
    heavy-tailed, and the extent, set by a few far points, says nothing of where
    the points are. On the Fig. 11 field at 200k rays, cutting the widest
    extent's axis gave 2 tiles a least halo of 14.4 % of the points, the widest
    interquartile range's 11.3 % (benchmarks/bench_tiles.py, docs/scaling.md).

    >>> x = np.array([0.0, 1, 2, 3, 4, 5, 6, 1e6])  # the widest extent, one point far
    >>> spread(np.column_stack([x, 2 * np.arange(8.0)]))
    array([3.5, 7. ])
    """
    q1, q3 = np.percentile(points, [25, 75], axis=0)
    iqr = q3 - q1
    return iqr if iqr.max() > 0 else points.max(axis=0) - points.min(axis=0)


@dataclass(frozen=True)
class Tiling:
    """A partition of R^D into boxes (a k-d tree of median cuts).

    Attributes
    ----------
    ndim : int
    axis, cut : ndarray, shape (ntiles - 1,)
        Per inner node: the coordinate cut and where (``x < cut`` goes low).
    low, high : ndarray of int64, shape (ntiles - 1,)
        Per inner node its children: an inner node (>= 0) or a tile ``-1 - t``.
    """

    ndim: int
    axis: np.ndarray
    cut: np.ndarray
    low: np.ndarray
    high: np.ndarray

    @property
    def ntiles(self) -> int:
        return len(self.axis) + 1

    @classmethod
    def split(cls, points, ntiles: int) -> "Tiling":
        """Cut ``points`` into ``ntiles`` boxes of equal counts (±1 per cut).

        Each cut halves a node's tiles (the low side gets ``floor(t/2)`` of them
        and that share of the points) across the node's axis of the widest
        interquartile range (:func:`spread`: the bulk's width, not the outliers';
        the halo follows the cut's area through the bulk), or where many points
        share the median there, the next widest axis whose median halves them
        (else the one that comes closest).

        Parameters
        ----------
        points : array_like, shape (n, D)
        ntiles : int
            At least 1.

        Returns
        -------
        Tiling
        """
        pts = as_array(points, "points", (None, "D"))
        if isinstance(ntiles, bool) or not isinstance(ntiles, (int, np.integer)) or ntiles < 1:
            raise InvalidInputError(f"tiles: expected an integer >= 1, got {ntiles!r}", "tiles")
        axis, cut, low, high = [], [], [], []

        def node(rows: np.ndarray, first: int, count: int) -> int:
            if count == 1:
                return -1 - first
            i = len(axis)
            axis.append(0), cut.append(0.0), low.append(0), high.append(0)
            k = count // 2
            if rows.size:
                sub = pts[rows]
                want = (len(rows) * k) // count
                best = None  # (how far the low side is from its share, axis, cut)
                for a in np.argsort(-spread(sub), kind="stable"):  # the widest first
                    vals = np.sort(sub[:, a])
                    at = float(vals[min(len(vals) - 1, want)])
                    off = abs(int(np.searchsorted(vals, at)) - want)
                    if best is None or off < best[0]:
                        best = (off, int(a), at)
                    if off <= 1:  # (points tied at the median: the next axis)
                        break
                _, ax, c = best
            else:
                ax, c = 0, 0.0
            go_low = pts[rows, ax] < c if rows.size else np.zeros(0, bool)
            axis[i], cut[i] = ax, c
            low[i] = node(rows[go_low], first, k)
            high[i] = node(rows[~go_low], first + k, count - k)
            return i

        node(np.arange(len(pts)), 0, int(ntiles))
        return cls(pts.shape[1], np.asarray(axis, np.int64), np.asarray(cut, np.float64),
                   np.asarray(low, np.int64), np.asarray(high, np.int64))

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Each tile's cell of the partition: ``lo, hi`` of shape (ntiles, D), ±inf on
        the outer sides (a tile's own points lie in it: ``lo <= x < hi``)."""
        T, D = self.ntiles, self.ndim
        lo, hi = np.full((T, D), -np.inf), np.full((T, D), np.inf)

        def walk(node: int, a: np.ndarray, b: np.ndarray) -> None:
            if node < 0:
                lo[-1 - node], hi[-1 - node] = a, b
                return
            ax, c = self.axis[node], self.cut[node]
            b2, a2 = b.copy(), a.copy()
            b2[ax], a2[ax] = min(b[ax], c), max(a[ax], c)
            walk(int(self.low[node]), a, b2)
            walk(int(self.high[node]), a2, b)

        if T == 1:
            return lo, hi
        walk(0, np.full(D, -np.inf), np.full(D, np.inf))
        return lo, hi

    def tile_of(self, points) -> np.ndarray:
        """The tile whose box holds each point, shape (n,) int64."""
        pts = np.asarray(points, dtype=np.float64)
        n = len(pts)
        if self.ntiles == 1:
            return np.zeros(n, np.int64)
        at = np.zeros(n, np.int64)  # inner node, or -1 - tile once at a leaf
        live = np.arange(n)
        while live.size:
            nd = at[live]
            go_low = pts[live, self.axis[nd]] < self.cut[nd]
            at[live] = np.where(go_low, self.low[nd], self.high[nd])
            live = live[at[live] >= 0]
        return -1 - at


@dataclass
class TileStats:
    """What the exchange did (:attr:`TiledTriangulation.stats`).

    Attributes
    ----------
    rounds : list of int
        Rounds of each exchange (one exchange for the inserts between two
        settles: :meth:`TiledTriangulation.settle`).
    sent : int
        Points sent between tiles so far.
    left_out : int
        Of those, the points their receiver left out (no neighbour of its own
        points: :meth:`flatserve.Triangulation.insert`'s ``neighbours_of``).
    forwarded : int
        Queries handed on to another tile so far.
    unresolved : int
        Queries answered after every hop failed to find an own cell (outside
        the hull only, where no tile is exact: a NaN either way).
    retiled : int
        Times the tiles were cut again because they had grown unequal.
    """

    rounds: list = field(default_factory=list)
    retiled: int = 0
    sent: int = 0
    left_out: int = 0
    forwarded: int = 0
    unresolved: int = 0


class Tile:
    """One tile of a :class:`TiledTriangulation`: its Delaunay triangulation (its own
    points and its halo, numbered by local sample ids) and which vertices are its
    own. Every call the tiled triangulation makes on a tile is a method here, with
    arrays in and arrays out, so that a tile may live in another process: a
    :class:`TileHost` makes and loads tiles, and a host that places them
    elsewhere hands back a proxy with these methods.

    Parameters
    ----------
    ndim : int
    tri : Triangulation, optional
        Default: an empty one.
    own : ndarray of uint8, shape (tri.npoints,), optional
        1 for an own vertex, 0 for a halo vertex.
    """

    def __init__(self, ndim: int, tri: Triangulation | None = None,
                 own: np.ndarray | None = None) -> None:
        self.tri = Triangulation(ndim) if tri is None else tri
        self.own = np.empty(0, np.uint8) if own is None else np.asarray(own, np.uint8)
        if self.tri.ndim != ndim:
            raise ValueError(f"a triangulation in R^{self.tri.ndim} for a tile in R^{ndim}")
        if len(self.own) != self.tri.npoints:
            raise ValueError(f"{self.tri.npoints} points for {len(self.own)} own flags")

    @property
    def npoints(self) -> int:
        return self.tri.npoints

    @property
    def generation(self) -> int:
        return self.tri.generation

    @property
    def nchannels(self) -> int:
        return self.tri.nchannels

    def insert(self, points: np.ndarray, values: np.ndarray | None, own: bool) -> InsertResult:
        """:meth:`flatserve.Triangulation.insert`; the new vertices are own points
        (``own``) or halo: of a halo, only the points that become neighbours of
        an own vertex (``neighbours_of``; the others: id -1)."""
        res = self.tri.insert(points, values, neighbours_of=None if own else self.own)
        k = self.tri.npoints - len(self.own)
        if k:
            self.own = np.concatenate([self.own, np.full(k, 1 if own else 0, np.uint8)])
        return res

    def take(self, local: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (n, D) and values (n, C) or None of local ids ``local`` (n,)."""
        vals = self.tri.values
        return self.tri.points[local], None if vals is None else vals[local]

    def own_flags(self) -> np.ndarray:
        """The own flags, uint8 (npoints,)."""
        return self.own.copy()

    def own_box(self) -> np.ndarray | None:
        """The bounding box of its own points, (2, D): min, max (None: none)."""
        own = self.own == 1
        if not own.any():
            return None
        p = self.tri.points[own]
        return np.stack([p.min(axis=0), p.max(axis=0)])

    def own_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The own flags (npoints,), and the own points' points and values (or None)."""
        own = self.own == 1
        vals = self.tri.values
        return self.own.copy(), self.tri.points[own], None if vals is None else vals[own]

    def conflicts(self, lo, hi, start, skip: int, **where) -> list[np.ndarray]:
        """:meth:`flatserve.Triangulation.conflicts` of its own vertices."""
        return self.tri.conflicts(self.own, lo, hi, start, skip=skip, **where)

    def answer(self, q, outside, order, threads, everywhere: bool):
        """:meth:`flatserve.Triangulation.interpolate_owned` from cells with an own
        vertex (``everywhere``: from any cell)."""
        own = np.ones(self.tri.npoints, np.uint8) if everywhere else self.own
        return self.tri.interpolate_owned(q, own, outside=outside, order=order, threads=threads)

    def locate(self, q, order, threads) -> Location:
        return self.tri.locate(q, order=order, threads=threads)

    def within(self, q, radius: float, threads) -> np.ndarray:
        """:meth:`flatserve.Triangulation.within` of its points (own and halo)."""
        return self.tri.within(q, radius, threads=threads)

    def count_cells(self) -> int:
        """:meth:`flatserve.Triangulation.count_cells` of its own vertices."""
        return self.tri.count_cells(self.own) if self.tri.npoints else 0

    def star_foreign(self) -> int:
        """Foreign vertices of the finite cells around its own vertices (the least
        halo: :meth:`TiledTriangulation.star_halo`)."""
        if self.tri.npoints <= self.tri.ndim:
            return 0
        s = self.tri.simplices
        own = self.own == 1
        v = np.unique(s[own[s].any(axis=1)])
        return int((~own[v]).sum())

    def record(self, gid: np.ndarray) -> bytes:
        """Its record in a snapshot (:meth:`TiledTriangulation.to_bytes`), given the
        global ids of its points (the tiled triangulation's bookkeeping): uint64 n,
        n int64 global ids, n uint8 own flags, uint64 length and
        :meth:`flatserve.Triangulation.to_bytes`."""
        gid = np.ascontiguousarray(gid, np.int64)
        if len(gid) != self.tri.npoints:
            raise ValueError(f"{len(gid)} global ids for a tile of {self.tri.npoints} points")
        blob = self.tri.to_bytes()
        return b"".join([np.uint64(len(gid)).tobytes(), gid.tobytes(), self.own.tobytes(),
                         np.uint64(len(blob)).tobytes(), blob])


def read_record(record) -> tuple[np.ndarray, np.ndarray, memoryview]:
    """A tile's record (:meth:`Tile.record`) read: its global ids, own flags and
    triangulation snapshot (a view of ``record``).

    Raises
    ------
    ValueError
        Truncated, or trailing bytes.
    """
    mv = memoryview(record)
    if _record_size(mv, 0) != len(mv):
        raise ValueError("trailing bytes after its record")
    n = int(np.frombuffer(mv[:8], np.uint64)[0])
    gid = np.frombuffer(mv[8:8 + 8 * n], np.int64).copy()
    own = np.frombuffer(mv[8 + 8 * n:8 + 9 * n], np.uint8).copy()
    return gid, own, mv[8 + 9 * n + 8:]


class TileHost:
    """Where a :class:`TiledTriangulation` keeps its tiles: this process (this
    class). A host that places tiles elsewhere (in cluster mode: a Ray actor per
    tile, :mod:`flatserve.service.cluster.worker.tiles`) returns objects with
    :class:`Tile`'s methods and attributes ``npoints``, ``generation``,
    ``nchannels``, and may have its tiles store and read their own snapshot parts
    (:meth:`part`, :meth:`load_part`); :func:`hosting` makes it the host of the
    tiled triangulations made meanwhile."""

    #: bytes of snapshot parts the tiles stored themselves (:meth:`part`): none here
    stored = 0

    def auto_tiles(self, nsamples: int) -> int:
        """How many tiles ``tiles="auto"`` gives a chart of ``nsamples`` samples here:
        in this process, one per core (:func:`auto_tiles`)."""
        return auto_tiles(nsamples)

    def map(self, fn, items):
        """``fn`` of each item, at once where the tiles allow it, in order: here on
        the shard pool's threads (the tiles' work is this process's)."""
        return shard_pool().map(fn, items)

    def make(self, ndim: int) -> Tile:
        """An empty tile."""
        return Tile(ndim)

    def load(self, ndim: int, record) -> tuple[Tile, np.ndarray, np.ndarray]:
        """A tile from its record (:meth:`Tile.record`), with the record's global ids
        and own flags.

        Raises
        ------
        ValueError
            A damaged record.
        """
        gid, own, snapshot = read_record(record)
        return Tile(ndim, Triangulation.from_bytes(snapshot), own), gid, own

    def load_part(self, ndim: int, key: str, parts, source: str, what: str
                  ) -> tuple[Tile, np.ndarray, np.ndarray]:
        """:meth:`load` of the snapshot part ``key``: ``parts(key)``, checked against
        its key (``source`` and ``what`` name it in the error). A host whose tiles
        read their own parts (in cluster mode) has each tile read its part where it
        lives.

        Raises
        ------
        flatserve.errors.SnapshotError
            The part's bytes are not its key's.
        """
        return self.load(ndim, read_part(parts, key, source, what))

    def part(self, tile: Tile, gid: np.ndarray, known) -> tuple[str, bytes | None]:
        """A tile's record (:meth:`Tile.record`) as a snapshot part: its key
        (:func:`flatserve.contract.part_key`) and its bytes, None when the part is
        stored already: its key is in ``known``, or (a host whose tiles store their
        own parts, in cluster mode) the tile stored it itself."""
        blob = tile.record(gid)
        key = part_key(blob)
        return key, None if key in known else blob


_HOST: ContextVar[TileHost | None] = ContextVar("flatserve_tile_host", default=None)


@contextmanager
def hosting(host: TileHost):
    """``with``: the tiled triangulations made (or loaded) in this context keep
    their tiles with ``host`` (for their whole life: a re-cut makes its tiles
    there too).

    >>> with hosting(TileHost()):
    ...     tt = TiledTriangulation(2, tiles=2)
    """
    token = _HOST.set(host)
    try:
        yield host
    finally:
        _HOST.reset(token)


class TiledTriangulation:
    """A Delaunay triangulation of points in R^D with values, over tiles (see the
    module doc): :class:`flatserve.Triangulation`'s ``insert`` and ``query``, the
    same answers bit for bit.

    Parameters
    ----------
    ndim : int
        D.
    tiles : int or "auto"
        Tiles; the :class:`Tiling` is cut from the first insert's points (or
        pass ``tiling``). ``"auto"``: the host's :meth:`TileHost.auto_tiles` of
        the points held (in this process :func:`auto_tiles`)
        (one tile to begin with), the tiles cut again from every point when it
        gives more tiles and either twice as many or the points have doubled
        since the last cut (so that the cuts cost at most about as much again as
        the inserts).
    tiling : Tiling, optional
    host : TileHost, optional
        Where the tiles live; default: the host of :func:`hosting`, else this
        process.

    Attributes
    ----------
    stats : TileStats
    """

    def __init__(self, ndim: int, tiles: int = 2, *, tiling: Tiling | None = None,
                 host: TileHost | None = None) -> None:
        self._ndim = int(Triangulation(ndim).ndim)
        self._host = host or _HOST.get() or TileHost()
        setting = tile_setting(tiles) if tiling is None else tiles
        self._auto = isinstance(setting, str)
        self._ntiles = tiling.ntiles if tiling is not None else 1 if self._auto else setting
        self.tiling = tiling
        self._empty(self._ntiles)
        self._tiled_at = 0
        self._channels: int | None = None
        self._lock = RWLock()
        self._stats_lock = threading.Lock()
        self.stats = TileStats()

    def _empty(self, T: int) -> None:
        """``T`` empty tiles (the tiling aside)."""
        self._ntiles = T
        self._tiles = [self._host.make(self._ndim) for _ in range(T)]
        self._gid = [np.empty(0, np.int64) for _ in range(T)]    # local id -> global id
        self._nown = np.zeros(T, np.int64)                       # own points per tile
        self._owner = np.empty(0, np.int64)                      # global id -> tile
        self._local = np.empty(0, np.int64)                      # global id -> local id there
        self._halo = [np.empty(0, np.int64) for _ in range(T)]   # foreign ids held, sorted
        self._parts: list = [None] * T    # tile -> (triangulation, generation, key) of its part
        self._reset_boxes()
        self._n = 0
        self._state = fresh_state()
        # seeds, generations and full flag of the inserts whose exchange has not run
        self._pending: tuple[list, list, bool] | None = None
        self._broken: str | None = None  # why an exchange failed

    def _reset_boxes(self) -> None:
        T, D = self._ntiles, self._ndim
        self._lo = np.full((T, D), np.inf)  # per tile: a box around its own points
        self._hi = np.full((T, D), -np.inf)

    def _grow_boxes(self, t: int, pts: np.ndarray) -> bool:
        """Tile ``t``'s box holds ``pts`` (its new own points); True if it grew
        (every cell must then be scanned again against it)."""
        if not len(pts):
            return False
        lo, hi = self._lo[t], self._hi[t]
        a, b = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
        out_lo, out_hi = a < lo, b > hi
        if not (out_lo.any() or out_hi.any()):
            return False
        if np.isfinite(lo).all():  # not the tile's first points: leave room in its cell
            ext = (b - a) * SLACK
            cell_lo, cell_hi = self.tiling.boxes()
            a = np.where(out_lo, np.maximum(a - ext, cell_lo[t]), a)
            b = np.where(out_hi, np.minimum(b + ext, cell_hi[t]), b)
        self._lo[t], self._hi[t] = a, b
        return True

    @property
    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """The boxes around the tiles' own points that the exchange tests balls
        against: ``lo, hi`` of shape (ntiles, D) (an empty tile's: +inf, -inf)."""
        return self._lo.copy(), self._hi.copy()

    def _boxes(self):
        """The tiles' boxes for :meth:`flatserve.Triangulation.conflicts` (one group
        of one box each)."""
        return self._lo, self._hi, np.arange(self._ntiles + 1, dtype=np.int64)

    # ------------------------------------------------------------------ access
    @property
    def ndim(self) -> int:
        return self._ndim

    @property
    def ntiles(self) -> int:
        """Tiles now (``tiles="auto"``: as many as :func:`auto_tiles` gave so far)."""
        return self._ntiles

    @property
    def auto(self) -> bool:
        """The tile count follows the points held (``tiles="auto"``)."""
        return self._auto

    @property
    def npoints(self) -> int:
        return self._n

    def __len__(self) -> int:
        return self._n

    @property
    def lock(self) -> RWLock:
        """Readers/writer lock: queries read, inserts (and their exchange) write."""
        return self._lock

    @property
    def tiles(self) -> tuple[Tile, ...]:
        """Each tile (own points and halo; local sample ids), settled
        (:meth:`settle`): a :class:`Tile` (its triangulation is ``.tri``), or what
        the host made in its place."""
        self.settle()
        return tuple(self._tiles)

    @property
    def host(self) -> TileHost:
        """Where the tiles live."""
        return self._host

    def global_ids(self, tile: int) -> np.ndarray:
        """Tile ``tile``'s local sample id -> global sample id, shape (its npoints,),
        settled."""
        with self._reading():
            return self._gid[tile].copy()

    def own(self, tile: int) -> np.ndarray:
        """Tile ``tile``'s local sample id -> its own point (True) or halo, bool,
        settled."""
        with self._reading():
            return self._tiles[tile].own_flags().astype(bool)

    @property
    def halo(self) -> np.ndarray:
        """Per tile, halo points held (foreign points), shape (ntiles,)."""
        with self._reading():
            return np.array([len(g) for g in self._gid], dtype=np.int64) - self._nown

    def star_halo(self) -> np.ndarray:
        """Per tile, the foreign vertices of its own vertices' finite cells: the
        least halo a tile answering exactly must hold (:attr:`halo` is what the
        exchange's conservative ball-box test gave it), shape (ntiles,)."""
        with self._reading():
            return np.array(list(self._host.map(lambda tile: tile.star_foreign(),
                                                  self._tiles)), dtype=np.int64)

    @property
    def own_counts(self) -> np.ndarray:
        """Per tile, own points, shape (ntiles,)."""
        return self._nown.copy()

    def _gather(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Every own point and its value (or None), row = global sample id."""
        parts = [(self._gid[t], *self._tiles[t].own_rows())
                 for t in range(self._ntiles) if self._nown[t]]
        if not parts:
            return None, None
        pts = np.empty((self._n, self._ndim))
        vals = np.empty((self._n, self._channels)) if self._channels else None
        for gid, own, p, v in parts:
            g = gid[own == 1]
            pts[g] = p
            if vals is not None:
                vals[g] = v
        return pts, vals

    @property
    def points(self) -> np.ndarray:
        """(npoints, D): row = global sample id."""
        with self._lock.read():
            p = self._gather()[0]
        return np.empty((0, self._ndim)) if p is None else p

    @property
    def values(self) -> np.ndarray | None:
        """(npoints, C) sample values (row = global sample id), or None."""
        with self._lock.read():
            return self._gather()[1] if self._channels else None

    @property
    def nchannels(self) -> int:
        return self._channels or 0

    @property
    def nsimplex(self) -> int:
        """Cells of the whole triangulation: each counted in the tile owning its
        lexicographically first vertex."""
        with self._reading():
            return sum(self._host.map(lambda tile: tile.count_cells(), self._tiles))

    # ------------------------------------------------------------------ insert
    def insert(self, points, values=None, *, settle: bool = False) -> InsertResult:
        """Insert points (and values): each into the tile whose box holds it. The
        exchange rounds that make every tile's own stars exact are left pending
        (:meth:`settle`): they run once for every insert in a row, before the
        tiles are next read; with ``settle``, at once, under the same write lock
        (no query comes in between, and a failing exchange fails the insert).

        Parameters
        ----------
        points : array_like, shape (n, D)
        values : array_like, shape (n, C), optional
            Required once the triangulation has values.

        Returns
        -------
        InsertResult
            Global sample ids (as :meth:`flatserve.Triangulation.insert` numbers them).
        """
        pts = as_array(points, "points", (None, self._ndim))
        n = len(pts)
        vals = None
        if values is not None:
            v = np.asarray(values, dtype=np.float64)
            if v.ndim == 1:
                v = v.reshape(-1, 1)
            vals = as_array(v, "values", (n, self._channels or "C"))
        if self._n and (vals is None) != (self._channels is None):
            raise InvalidInputError("values: required, shape (n, C), as in the first insert"
                                    if vals is None else
                                    "values: this triangulation was built without values",
                                    "values")
        with self._lock.write(), self._breaking():
            self._state = fresh_state()  # (whatever the insert changes)
            self._check_whole()
            if self.tiling is None:
                if self._auto and self._n == 0:  # a first batch large enough: cut at once
                    self._empty(self._host.auto_tiles(len(pts)))
                self.tiling = Tiling.split(pts, self._ntiles)
                self._tiled_at = len(pts)
            if vals is not None:
                self._channels = vals.shape[1]
            res = self._insert(pts, vals)
            want = self._host.auto_tiles(self._n) if self._auto else self._ntiles
            if want > self._ntiles and (want >= 2 * self._ntiles or self._n >= 2 * self._tiled_at):
                self._retile(want)  # (each cut: the tiles or the points have doubled)
            elif self._unequal():
                self._retile()
            if settle:
                self._settle()
            return res

    def _unequal(self) -> bool:
        """Re-tile when the largest tile holds more than :data:`RETILE_SHARE` times its
        share and the points have doubled since the tiling was cut (so re-tiling
        costs at most as much again as the inserts themselves)."""
        T = self._ntiles
        return (T > 1 and self._n >= 2 * self._tiled_at
                and int(self.own_counts.max()) > RETILE_SHARE * self._n / T)

    def _retile(self, tiles: int | None = None) -> None:
        """Cut a new tiling (of ``tiles``, default as many as now) from every point
        and build the tiles again (sample ids, values and answers unchanged)."""
        pts, vals = self._gather()
        self._empty(self._ntiles if tiles is None else int(tiles))  # (no exchange pending)
        self.tiling = Tiling.split(pts, self._ntiles)
        self._tiled_at = len(pts)
        self._insert(pts, vals)
        self.stats.retiled += 1

    def _insert(self, pts: np.ndarray, vals: np.ndarray | None) -> InsertResult:
        T, n = self._ntiles, len(pts)
        where = self.tiling.tile_of(pts)
        rows = [np.flatnonzero(where == t) for t in range(T)]
        before = [tri.npoints for tri in self._tiles]
        gens = [tri.generation for tri in self._tiles]

        def put(t):
            r = rows[t]
            if not r.size:
                return None
            return self._tiles[t].insert(pts[r], None if vals is None else vals[r], True)

        got = list(self._host.map(put, range(T)))
        # global ids: new points numbered in input row order (first occurrence)
        fresh_rows, fresh_tile, fresh_local = [], [], []
        for t, res in enumerate(got):
            if res is None:
                continue
            new = res.ids >= before[t]
            _, first = np.unique(res.ids, return_index=True)
            first_mask = np.zeros(len(res.ids), bool)
            first_mask[first] = True
            sel = new & first_mask
            fresh_rows.append(rows[t][sel])
            fresh_tile.append(np.full(int(sel.sum()), t, np.int64))
            fresh_local.append(res.ids[sel])
        fr = np.concatenate(fresh_rows) if fresh_rows else np.empty(0, np.int64)
        ft = np.concatenate(fresh_tile) if fresh_tile else np.empty(0, np.int64)
        fl = np.concatenate(fresh_local) if fresh_local else np.empty(0, np.int64)
        order = np.argsort(fr, kind="stable")
        fr, ft, fl = fr[order], ft[order], fl[order]
        g0 = self._n
        gids = g0 + np.arange(len(fr), dtype=np.int64)
        m = g0 + len(fr)
        self._owner = np.concatenate([self._owner, ft])
        self._local = np.concatenate([self._local, fl])
        self._n = m
        seeds: list = [None] * T
        grew = False
        for t in range(T):
            k = self._tiles[t].npoints - before[t]
            if k:
                sel = ft == t
                # the tile numbered its new vertices in its row order = global order
                g = np.empty(k, np.int64)
                g[fl[sel] - before[t]] = gids[sel]
                self._gid[t] = np.concatenate([self._gid[t], g])
                self._nown[t] += k
                seeds[t] = np.arange(before[t], before[t] + k, dtype=np.int64)
            if k:
                grew |= self._grow_boxes(t, pts[fr[sel]])
        ids = np.empty(n, np.int64)
        for t, res in enumerate(got):
            if res is not None:
                ids[rows[t]] = self._gid[t][res.ids]
        n_new = len(fr)
        if vals is not None and n_new < n:
            self._revalue(ids, vals)
        self._defer(seeds, gens, grew)
        ids.flags.writeable = False
        return InsertResult(ids=ids, n_new=n_new, n_duplicates=n - n_new)

    def _defer(self, seeds: list, gens: list, full: bool) -> None:
        """Add an insert's new own vertices to the pending exchange (the first
        pending insert's generations stay: the scan covers every insert since)."""
        if self._pending is None:
            self._pending = (seeds, gens, full)
            return
        s0, g0, f0 = self._pending
        merged = [b if a is None else a if b is None else np.concatenate([a, b])
                  for a, b in zip(s0, seeds)]
        self._pending = (merged, g0, f0 or full)

    @property
    def settled(self) -> bool:
        """False while inserts wait for their exchange (:meth:`settle`)."""
        return self._pending is None

    def settle(self) -> None:
        """Run the exchange rounds of every insert since the last exchange (a writer;
        nothing to do when :attr:`settled`). Queries and snapshots call it; an
        owner that inserts in bursts may call it when a burst ends, so that the
        next query does not pay for it."""
        if self._pending is None:
            return
        with self._lock.write():
            self._settle()

    def _settle(self) -> None:
        """Under the write lock (see :meth:`_breaking`)."""
        self._check_whole()
        if self._pending is not None:
            seeds, gens, full = self._pending
            with self._breaking():
                self._exchange(seeds, list(gens), full=full)
            self._pending = None

    @contextmanager
    def _breaking(self):
        """``with``, under the write lock: an insert, a re-cut or an exchange that
        raises part-way leaves tiles that may hold points their bookkeeping does
        not account for: the triangulation is then broken, and every later use
        raises (its owner rebuilds it: the service does, from its log), never
        answering from inexact tiles."""
        try:
            yield
        except BaseException as exc:
            self._broken = self._broken or f"{type(exc).__name__}: {exc}"
            raise

    def _check_whole(self) -> None:
        if self._broken is not None:
            raise RuntimeError(f"tiles: an exchange failed ({self._broken}); this "
                               "triangulation must be built again")

    def _read_settled(self, blocking: bool = True) -> bool:
        """Take the read lock on settled tiles (settling them first): True when
        held; False (``blocking=False``) when that would wait."""
        while True:
            if blocking:
                self._lock.acquire_read()
            elif not self._lock.try_acquire_read():
                return False
            if self._pending is None and self._broken is None:
                return True
            self._lock.release_read()
            if not blocking:
                return False
            with self._lock.write():
                self._settle()

    @contextmanager
    def _reading(self):
        """``with``: the read lock on settled tiles."""
        self._read_settled()
        try:
            yield
        finally:
            self._lock.release_read()

    def _revalue(self, ids: np.ndarray, vals: np.ndarray) -> None:
        """A duplicate's value replaces the stored one in every halo holding it (the
        owner's was replaced by its insert): re-inserted there, it lands on its
        vertex."""
        rev = ids[::-1]
        g, first = np.unique(rev, return_index=True)
        last = len(ids) - 1 - first
        for t in range(self._ntiles):
            halo = _among(self._halo[t], g)
            if halo.any():
                hg = g[halo]
                self._tiles[t].insert(self._points_of(hg)[0], vals[last[halo]], False)

    def _holds(self, t: int, g: np.ndarray) -> np.ndarray:
        """Whether tile ``t`` holds each global id of ``g`` (bool, shape of ``g``):
        its own points, and its halo (sorted foreign ids: 8 bytes a halo point
        rather than a byte per sample and tile)."""
        return (self._owner[g] == t) | _among(self._halo[t], g)

    def _points_of(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The points (n, D) and values (n, C) or None of global ids ``g``, from their
        owners."""
        pts = np.empty((len(g), self._ndim))
        vals = np.empty((len(g), self._channels)) if self._channels else None
        own = self._owner[g]
        for t in np.unique(own):
            sel = own == t
            p, v = self._tiles[t].take(self._local[g[sel]])
            pts[sel] = p
            if vals is not None:
                vals[sel] = v
        return pts, vals

    def _exchange(self, seeds: list, gens: list, *, full: bool) -> None:
        """Rounds of Tile & Merge until no tile receives a new point. ``seeds[t]``:
        tile ``t``'s vertices new since its last scan (None: none), made by its
        inserts after generation ``gens[t]``; ``full``: every cell is scanned."""
        T = self._ntiles
        rounds = 0
        # per tile, the points it left out in this exchange: never needed while
        # its own points stay the same (Triangulation.insert's neighbours_of)
        left = [np.empty(0, np.int64) for _ in range(T)]
        if T > 1:
            lo, hi, start = self._boxes()
            while True:
                def scan(t):
                    tile = self._tiles[t]
                    if not tile.npoints or (not full and seeds[t] is None):
                        return None
                    if full:
                        where = {}
                    elif len(seeds[t]) > SCAN_SHARE * tile.npoints:
                        where = {"since": gens[t]}
                    else:
                        where = {"seeds": seeds[t]}
                    return tile.conflicts(lo, hi, start, t, **where)

                found = list(self._host.map(scan, range(T)))
                recv: list = [[] for _ in range(T)]
                for t, per_box in enumerate(found):
                    if per_box is None:
                        continue
                    for b in range(T):
                        if b != t and per_box[b].size:
                            g = self._gid[t][per_box[b]]
                            recv[b].append(g[~self._holds(b, g) & ~_among(left[b], g)])
                todo = [np.unique(np.concatenate(r)) if r else np.empty(0, np.int64)
                        for r in recv]
                if not any(len(g) for g in todo):
                    break
                rounds += 1

                def take(b):
                    g = todo[b]
                    if not len(g):
                        return None
                    tile = self._tiles[b]
                    k0 = tile.npoints
                    gens[b] = tile.generation
                    res = tile.insert(*self._points_of(g), False)
                    if res.n_duplicates:  # a point of another tile equal to one here
                        raise RuntimeError("tiles: a point held by two tiles as its own")
                    return res.ids - k0  # (new vertices k0, k0 + 1, ...; -1 - k0 left out)

                got = list(self._host.map(take, range(T)))
                seeds = [None] * T
                for b, g in enumerate(todo):
                    if len(g):
                        at = got[b]
                        kept = at >= 0
                        added = np.empty(int(kept.sum()), np.int64)
                        added[at[kept]] = g[kept]
                        if len(added):
                            seeds[b] = self._gid[b].size + np.arange(len(added), dtype=np.int64)
                        self._gid[b] = np.concatenate([self._gid[b], added])
                        self._halo[b] = np.union1d(self._halo[b], g[kept])
                        left[b] = np.union1d(left[b], g[~kept])
                        self.stats.sent += len(g)
                        self.stats.left_out += int((~kept).sum())
                full = False
        self.stats.rounds.append(rounds)

    # ------------------------------------------------------------------ queries
    def query(self, xi, outside: Outside | str = Outside.NAN, order: Order | str = Order.HILBERT,
              threads: int | None = None, *, locate: bool = False, blocking: bool = True,
              then=None):
        """:meth:`flatserve.Triangulation.query` over the tiles: each query answered by
        a tile that holds its cell exactly (see the module doc). ``then`` as there:
        its :class:`~flatserve.triangulation.Held` arrays gather every tile's own
        points and values (a copy of the chart; from other processes when the
        tiles live there).

        Returns
        -------
        (values, inside, Location or None), or None (``blocking=False`` and an
        insert holds the triangulation). A location's ids are global sample ids,
        its weights in the tile's vertex order of the cell, its ``simplex`` -1.
        """
        q = as_array(xi, "xi", (None, self._ndim))
        outside = choice(outside, Outside, "outside")
        order = choice(order, Order, "order")
        if not self._channels:
            raise InvalidInputError("values: the triangulation has no values", "values")
        if not self._read_settled(blocking):
            return None
        try:
            out, inside, loc = self._query(q, outside, order, threads, locate)
            if then is not None:
                out = then(out, inside, loc, Held(self._state, self._gather))
            return out, inside, loc
        finally:
            self._lock.release_read()

    def within(self, xi, radius: float, threads: int | None = None) -> np.ndarray:
        """:meth:`flatserve.Triangulation.within` over the tiles (a halo vertex is a
        sample too): xi (..., D), bool (...,)."""
        arr = np.asarray(xi, dtype=np.float64) if not isinstance(xi, np.ndarray) else xi
        if arr.ndim == 0 or arr.shape[-1] != self._ndim:
            raise InvalidInputError(f"xi: expected shape (..., {self._ndim}), got "
                                    f"{np.shape(arr)}", "xi")
        lead = arr.shape[:-1]
        q = as_array(arr.reshape(-1, self._ndim), "xi", (None, self._ndim))
        radius = check_radius(radius)
        out = np.zeros(len(q), dtype=bool)
        with self._lock.read():
            for t in range(self._ntiles):
                todo = np.flatnonzero(~out)
                if not todo.size:
                    break
                if self._tiles[t].npoints:
                    out[todo] = self._tiles[t].within(q[todo], radius, threads)
        return out.reshape(lead)

    def interpolate(self, xi, outside: Outside | str = Outside.NAN,
                    order: Order | str = Order.HILBERT, threads: int | None = None):
        """Values (n, C) and inside (n,) (:meth:`flatserve.Triangulation.interpolate`)."""
        v, inside, _ = self.query(xi, outside=outside, order=order, threads=threads)
        return v, inside

    def _query(self, q, outside, order, threads, locate):
        T, n = self._ntiles, len(q)
        out = np.full((n, self._channels), np.nan)
        inside = np.zeros(n, dtype=bool)
        by = np.full(n, -1, np.int64)  # the tile that answered
        if n == 0 or self._n == 0:
            return out, inside, self._no_location(n) if locate else None
        at = self.tiling.tile_of(q)
        todo = np.arange(n)
        hops = 0
        forwarded = unresolved = 0
        while todo.size:
            last = hops >= T  # every tile had its chance: answer where it is
            groups = [todo[at[todo] == t] for t in range(T)]

            def ask(t):
                r = groups[t]
                tile = self._tiles[t]
                if not r.size or not tile.npoints:
                    return None
                return tile.answer(q[r], outside, order, threads, last)

            nxt = []
            for t, res in enumerate(self._host.map(ask, range(T))):
                r = groups[t]
                if res is None:
                    if r.size and not self._tiles[t].npoints and not last:
                        # an empty tile: hand on to any tile holding points
                        at[r] = (t + 1) % T
                        nxt.append(r)
                    continue
                v, ins, fwd = res
                done = fwd < 0
                out[r[done]] = v[done]
                inside[r[done]] = ins[done]
                by[r[done]] = t
                if (~done).any():
                    rr = r[~done]
                    at[rr] = self._owner[self._gid[t][fwd[~done]]]
                    nxt.append(rr)
            todo = np.concatenate(nxt) if nxt else np.empty(0, np.int64)
            if hops == 0:
                forwarded = len(todo)
            if last:
                unresolved = len(todo)
                break
            hops += 1
        with self._stats_lock:
            self.stats.forwarded += forwarded
            self.stats.unresolved += unresolved
        loc = self._locate(q, by, order, threads) if locate else None
        return out, inside, loc

    def _no_location(self, n: int) -> Location:
        D1 = self._ndim + 1
        return Location(ids=np.full((n, D1), -1, np.int64), weights=np.full((n, D1), np.nan),
                        kind=np.full(n, int(LocateKind.OUTSIDE_AFFINE_HULL), np.int8), simplex=np.full(n, -1, np.int64))

    def _locate(self, q, by, order, threads) -> Location:
        loc = self._no_location(len(q))
        for t in range(self._ntiles):
            r = np.flatnonzero(by == t)
            if not r.size:
                continue
            got = self._tiles[t].locate(q[r], order=order, threads=threads)
            ids = got.ids
            g = np.where(ids >= 0, self._gid[t][np.maximum(ids, 0)], -1)
            loc.ids[r], loc.weights[r], loc.kind[r] = g, got.weights, got.kind
        return loc

    # ------------------------------------------------------------------ snapshots
    @staticmethod
    def setting_of(tiling: dict) -> int | str:
        """The ``tiles`` a :meth:`tiling_dict` was made with: its count, or ``"auto"``."""
        return "auto" if tiling.get("auto") else int(tiling["tiles"])

    def tiling_dict(self) -> dict:
        """The tiling as JSON-able lists (a field file's metadata)."""
        tl = self.tiling
        out = {"tiles": self._ntiles, **({"auto": True} if self._auto else {})}
        return out if tl is None else {**out, "axis": tl.axis.tolist(), "cut": tl.cut.tolist(),
                                       "low": tl.low.tolist(), "high": tl.high.tolist()}

    def to_bytes(self) -> bytes:
        """Every tile's own snapshot, with its global ids and own flags.

        Layout: uint64 tiles, then per tile its record: uint64 n, n int64 global
        ids, n uint8 own flags, uint64 length and the tile's triangulation
        snapshot (:meth:`flatserve.Triangulation.to_bytes`). The tiling itself
        travels in the field file's metadata (:meth:`tiling_dict`).
        """
        with self._reading():
            return b"".join([np.uint64(self._ntiles).tobytes(),
                             *(self._tiles[t].record(self._gid[t])
                               for t in range(self._ntiles))])

    def tile_parts(self, known=()) -> list[tuple[str, bytes | None]]:
        """Each tile's record (:meth:`to_bytes`) as a snapshot part: per tile its
        key (:func:`flatserve.contract.part_key` of the record) and the record,
        None when the part is stored already (:meth:`TileHost.part`: the key is in
        ``known``, or the tile stored it itself); a tile unchanged since its part
        was last made (the same triangulation at the same
        :attr:`~flatserve.Triangulation.generation`) whose key is known is not
        serialised again. One moment of the tiles (the read lock), serialised at
        once where the host keeps them.

        Parameters
        ----------
        known : collection of str
            Keys of the parts stored already.
        """
        known = frozenset(known)

        def part(t: int):
            tile, last = self._tiles[t], self._parts[t]
            if last is not None and last[0] is tile and last[1] == tile.generation and \
                    last[2] in known:
                return last[2], None
            gen = tile.generation
            key, blob = self._host.part(tile, self._gid[t], known)
            self._parts[t] = (tile, gen, key)
            return key, blob

        with self._reading():
            return list(self._host.map(part, range(self._ntiles)))

    @classmethod
    def from_bytes(cls, data, ndim: int, tiling: dict) -> "TiledTriangulation":
        """Inverse of :meth:`to_bytes` (``tiling``: :meth:`tiling_dict`).

        Raises
        ------
        ValueError
            The bytes do not hold the tiles the tiling names (the caller says
            which file: :class:`~flatserve.errors.SnapshotError`).
        """
        mv = memoryview(data)
        if len(mv) < 8:
            raise ValueError("truncated tiles")
        T = int(np.frombuffer(mv[:8], np.uint64)[0])
        if T != int(tiling["tiles"]):
            raise ValueError("the tile count differs from the tiling's")
        records, at = [], 8
        for _ in range(T):
            size = _record_size(mv, at)
            records.append(mv[at:at + size])
            at += size
        if at != len(mv):
            raise ValueError("trailing bytes after the tiles")
        self = cls._of_tiling(ndim, tiling)
        return self._assemble(lambda t: self._host.load(self._ndim, records[t]))

    @classmethod
    def from_parts(cls, parts, keys, ndim: int, tiling: dict,
                   source: str = "tiles") -> "TiledTriangulation":
        """The tiles from their snapshot parts (:meth:`tile_parts`), in tile order:
        ``parts(key) -> bytes`` each tile's record, read where the host keeps the
        tile (:meth:`TileHost.load_part`), each checked against its key. A tile
        unchanged since is not serialised again by :meth:`tile_parts`.

        Raises
        ------
        ValueError
            As :meth:`from_bytes`.
        flatserve.errors.SnapshotError
            A part's bytes are not its key's (``source`` names the file).
        """
        self = cls._of_tiling(ndim, tiling)
        if len(keys) != self._ntiles:
            raise ValueError("the tile count differs from the tiling's")
        keys = [str(k) for k in keys]
        self._assemble(lambda t: self._host.load_part(
            self._ndim, keys[t], parts, source, f"the part of tile {t}"))
        for t, tile in enumerate(self._tiles):
            self._parts[t] = (tile, tile.generation, keys[t])
        return self

    @classmethod
    def _of_tiling(cls, ndim: int, tiling: dict) -> "TiledTriangulation":
        """An empty triangulation of the tiling's tiles (:meth:`tiling_dict`)."""
        T = int(tiling["tiles"])
        tl = None
        if "axis" in tiling:
            tl = Tiling(int(ndim), *(np.asarray(tiling[k], dt) for k, dt in
                                     (("axis", np.int64), ("cut", np.float64),
                                      ("low", np.int64), ("high", np.int64))))
            if tl.ntiles != T:
                raise ValueError(f"a tiling of {tl.ntiles} tiles named {T}")
        self = cls(ndim, cls.setting_of(tiling), tiling=tl)
        self._empty(T)
        return self

    def _assemble(self, load) -> "TiledTriangulation":
        """The tiles ``load(t) -> (tile, global ids, own flags)``, loaded at once (on
        the cores, or where the host puts them), and their bookkeeping."""
        T = self._ntiles
        got = list(self._host.map(load, range(T)))
        self._tiles = [tile for tile, _, _ in got]
        owner, local = [], []
        for t, (tile, gid, owns) in enumerate(got):
            self._gid[t] = gid
            n = len(gid)
            if tile.npoints != n:
                raise ValueError(f"tile {t}: {tile.npoints} points for {n} ids")
            own = owns == 1
            self._nown[t] = int(own.sum())
            owner.append((gid[own], t))
            local.append(np.flatnonzero(own))
            if own.any():
                self._grow_boxes(t, tile.own_box())
            if tile.nchannels:
                self._channels = tile.nchannels
        del got
        m = sum(len(g) for g, _ in owner)
        self._n = self._tiled_at = m
        self._state = fresh_state()
        self._owner = np.full(m, -1, np.int64)
        self._local = np.full(m, -1, np.int64)
        for (g, t), loc in zip(owner, local):
            if (g < 0).any() or (g >= m).any():
                raise ValueError("a global id out of range")
            self._owner[g], self._local[g] = t, loc
        if (self._owner < 0).any():
            raise ValueError("a sample owned by no tile")
        for t in range(T):
            if (self._gid[t] < 0).any() or (self._gid[t] >= m).any():
                raise ValueError("a global id out of range")
            self._halo[t] = np.sort(self._gid[t][self._owner[self._gid[t]] != t])
        return self

    def __repr__(self) -> str:
        return (f"TiledTriangulation(ndim={self._ndim}, tiles={self._ntiles}"
                f"{' (auto)' if self._auto else ''}, "
                f"npoints={self._n}, halo={sum(len(g) for g in self._gid) - int(self._nown.sum())})")


def _among(sorted_ids: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``np.isin(g, sorted_ids)`` for sorted ``sorted_ids`` (a binary search each)."""
    if not len(sorted_ids):
        return np.zeros(np.shape(g), bool)
    at = np.searchsorted(sorted_ids, g)
    return sorted_ids[np.minimum(at, len(sorted_ids) - 1)] == g


def _record_size(mv: memoryview, at: int) -> int:
    """The length of the tile record at ``at`` (:meth:`TiledTriangulation.to_bytes`);
    ValueError if it does not fit in ``mv``."""
    if at + 8 > len(mv):
        raise ValueError("truncated tiles")
    n = int(np.frombuffer(mv[at:at + 8], np.uint64)[0])
    head = 8 + 9 * n
    if at + head + 8 > len(mv):
        raise ValueError("truncated tiles")
    size = int(np.frombuffer(mv[at + head:at + head + 8], np.uint64)[0])
    if at + head + 8 + size > len(mv):
        raise ValueError("truncated tiles")
    return head + 8 + size
