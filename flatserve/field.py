"""A function sampled on flats: a basis + a triangulation + sample values.

This is the paper's Sec. 5 pipeline in one object. Samples (flats with values)
are turned into affine coordinates in a :class:`~flatserve.basis.Basis`
(Sec. 4, Eq. 9 and 12); samples whose coordinates do not round-trip lie outside
the chart the basis spans and are *rejected with a reason*, never triangulated
silently. The accepted coordinates are embedded in R^(m-1) through a regular
simplex (Sec. 5) and inserted into a CGAL Delaunay triangulation whose vertices
carry the values. A query flat goes through the same coordinates and embedding,
is located by a walk, and its value is the barycentric interpolation of the
values at the vertices of its simplex.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from typing import Collection, NamedTuple, Sequence

import numpy as np

from ._fieldbase import FieldBase, corrupted, pack_header, read_header, write_part
from .basis import Basis
from .coordinates import NO_SAMPLES, OK, ROUNDTRIP_TOL, reason
from .embedding import embed
from .errors import InvalidInputError, SnapshotError
from .gradient import gradient_chunk, slopes, taylor_blend
from .options import Interpolant, Order, Outside, choice
from .flats import Flats, check_batch
from .tiles import TiledTriangulation, tile_setting
from .triangulation import MAX_NDIM, Triangulation
from .warp import FlatWarp, LineWarp, warp_from_dict

__all__ = ["FIELD_MAGIC", "Field", "AddResult", "Chart", "PreparedBatch", "QueryResult", "QueryRoute"]


@dataclass(frozen=True)
class AddResult:
    """Outcome of :meth:`Field.add`.

    Attributes
    ----------
    accepted : int
        Number of input rows inserted (duplicates included: their value
        replaced the earlier one).
    rejected : (j,) int64
        Indices (into the input batch) of rows that were not inserted.
    reasons : list of str
        One human-readable reason per rejected row.
    duplicates : int
        Accepted rows whose embedded coordinates coincided with an existing
        vertex; policy: the later value replaces the earlier one.
    nsamples : int
        Number of distinct samples (vertices) in the field afterwards.
    """

    accepted: int
    rejected: np.ndarray
    reasons: list[str]
    duplicates: int
    nsamples: int


@dataclass(frozen=True)
class PreparedBatch:
    """A batch charted by :meth:`Field.prepare` and not yet inserted.

    Attributes
    ----------
    nrows : int
        Rows in the input batch.
    x : (a, D) float64
        Embedded coordinates of the accepted rows.
    values : (a, C) float64
        Their values.
    rejected : (j,) int64
        Indices (into the input batch) of rows that will not be inserted.
    reasons : list of str
        One reason per rejected row.
    """

    nrows: int
    x: np.ndarray
    values: np.ndarray
    rejected: np.ndarray
    reasons: list[str]

    @property
    def accepted(self) -> int:
        return int(self.x.shape[0])


def _spans(tri, ndim: int) -> bool:
    """Whether a chart's triangulation has a simplex to answer from: more than
    ``ndim`` samples, not all in one hyperplane (its ``current_dimension``, when the
    triangulation tells it)."""
    if tri.npoints <= ndim:
        return False
    dim = getattr(tri, "current_dimension", None)
    return dim is None or dim >= ndim


@dataclass(frozen=True)
class QueryResult:
    """Outcome of :meth:`Field.query` (and of the HTTP client's queries).

    Attributes
    ----------
    values : (q, C) float64
        Interpolated values; NaN where ``inside`` is False (unless
        ``outside="clamp"`` found a hull facet).
    inside : (q,) bool
        The query's coordinates round-trip and lie inside the convex hull of
        the samples.
    status : (q,) int8 or None
        Status per query (:class:`flatserve.coordinates.Status`): ``OK`` where
        the coordinates round-trip in a chart whose samples span a simplex
        (then ``inside`` says whether the query lies in their hull);
        ``NO_SAMPLES`` where they round-trip but the chart, or every chart of
        an atlas that holds the query, has too few samples to span one;
        ``NOT_REPRESENTABLE`` (``SINGULAR``, ``AMBIGUOUS``) where no chart
        holds it. None where an HTTP response did not carry it (a ``.npy``
        answer asked without ``status=true``).
    ids : (q, D+1) int64 or None
        Sample ids of the simplex's vertices (−1 for none), if requested.
    weights : (q, D+1) float64 or None
        Barycentric weights, if requested.
    """

    values: np.ndarray
    inside: np.ndarray
    status: np.ndarray
    ids: np.ndarray | None = None
    weights: np.ndarray | None = None


class QueryRoute(NamedTuple):
    """Which shards answer which of ``n`` queries, and with what weight (``route_query``).

    ``rows[i]`` (int64, increasing) are the queries shard ``i`` answers and
    ``weights[i]`` (float64, the same length) their blending weights, before
    the rows the shard cannot answer are dropped (all 1 for a one-chart field).
    """

    #: queries in the batch
    n: int
    #: per shard, row indices
    rows: list
    #: per shard, one weight per row
    weights: list


@dataclass(frozen=True)
class Chart:
    """Flats expressed in a field's chart: :meth:`Field.chart`.

    Attributes
    ----------
    status : (n,) int8
        Coordinate status per flat (:data:`flatserve.coordinates.OK`, ...).
    points : (a, D) float64
        Embedded coordinates (paper Sec. 5) of the flats whose status is OK,
        in their order (``a`` = number of OK rows, ``D = m - 1``).
    residual : (n,) float64
        Round-trip residual per flat (NaN where none was computed).
    seconds : float
        Time taken to chart.
    """

    status: np.ndarray
    points: np.ndarray
    residual: np.ndarray
    seconds: float = 0.0

    @property
    def ok(self) -> np.ndarray:
        """(n,) bool: the coordinates round-trip (status OK)."""
        return self.status == OK

    def __len__(self) -> int:
        return int(self.status.shape[0])

    def take(self, rows: np.ndarray) -> "Chart":
        """The chart of the flats at ``rows`` (an index array), in that order."""
        rows = np.asarray(rows, dtype=np.intp)
        ok = self.ok
        rank = np.cumsum(ok) - 1
        keep = ok[rows]
        return Chart(self.status[rows], self.points[rank[rows[keep]]], self.residual[rows],
                     self.seconds)


#: The first 8 bytes of a field file (:meth:`Field.write_to`).
FIELD_MAGIC = b"FSFIELD\x00"
_VERSION = 1
#: The version of a field file with a warp (its points are warped: a reader of
#: version 1 would chart its queries without it). Both are read.
_VERSION_WARP = 2
#: The version of a field file whose chart is split into tiles (its payload is
#: :meth:`flatserve.tiles.TiledTriangulation.to_bytes`, the tiling in the
#: metadata; with or without a warp). All three are read.
_VERSION_TILES = 3


def _kd_tree():
    """scipy's ``cKDTree`` (the gradient interpolant's neighbours), or an ImportError
    naming the extra that brings it."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:  # the library alone brings NumPy only
        raise ImportError("interpolant 'gradient' needs SciPy: pip install "
                          "'flatserve[gradient]'") from None
    return cKDTree


class Field(FieldBase):
    """Values sampled on k-flats in R^d, interpolated piecewise linearly.

    The one place where flats become interpolated values: :meth:`chart`
    (flats to embedded coordinates), :meth:`prepare` + :meth:`insert_prepared`
    (= :meth:`add`), :meth:`query`. Flats are given as a
    :class:`~flatserve.flats.Flats` batch (any form: rays, parametric,
    quadrics); :meth:`add_rays` and :meth:`query_rays` are one-line
    conveniences for lines.

    Thread safety (as scipy.spatial): any number of threads may call the
    readers (:meth:`chart`, :meth:`query`, :meth:`prepare`, :meth:`save`) at
    once, but a writer (:meth:`insert_prepared`, :meth:`add`) must not run
    beside any other call. The service guards each field with one
    readers/writer lock.

    A Field is one *shard* of the field contract
    (:class:`flatserve.contract.SampledField`): ``shards == (self,)``, its
    routing sends every row to itself and its blend is its own answer.

    Parameters
    ----------
    basis : Basis
        The m flats whose affine coordinates chart the samples.
    channels : int
        Number of values per sample (1 for grey, 3 for RGB).
    roundtrip_tol : float
        Largest round-trip residual (see :func:`flatserve.coordinates.coordinates`)
        for which a sample's or query's coordinates are trusted.
    warp : flatserve.warp.LineWarp or flatserve.warp.FlatWarp, optional
        Applied to the embedded points before they are triangulated (the
        isometric charts of an atlas, :mod:`flatserve.warp`: a
        :class:`~flatserve.warp.LineWarp` for lines, a
        :class:`~flatserve.warp.FlatWarp` for k-flats of any k >= 1);
        None (the default): the paper's chart.
    tiles : int or "auto"
        Split the chart's triangulation into this many tiles
        (:mod:`flatserve.tiles`, Tile & Merge: built on the cores at once, the
        same answers bit for bit); 1 (the default): one triangulation;
        ``"auto"``: one tile per core once the chart is large enough to gain
        from it (:func:`flatserve.tiles.auto_tiles`).

    Examples
    --------
    >>> import numpy as np, flatserve
    >>> basis = flatserve.Basis.around_axis(axis=2, scale=0.01)
    >>> field = flatserve.Field(basis, channels=1)
    >>> rng = np.random.default_rng(0)
    >>> eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (2000, 3))
    >>> screen = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    >>> res = field.add(flatserve.Flats.from_rays(eyes, screen - eyes), screen[:, :1])
    >>> out = field.query_rays(eyes[:5], screen[:5] - eyes[:5])
    """

    def __init__(self, basis: Basis, channels: int = 1, *, roundtrip_tol: float = ROUNDTRIP_TOL,
                 warp: LineWarp | FlatWarp | None = None, tiles: int | str = 1):
        if not isinstance(basis, Basis):
            raise InvalidInputError(f"basis: expected a flatserve.Basis, got {type(basis).__name__}", "basis")
        if not (isinstance(channels, (int, np.integer)) and channels >= 1):
            raise InvalidInputError(f"channels: expected a positive integer, got {channels!r}", "channels")
        if not (np.isfinite(roundtrip_tol) and roundtrip_tol > 0):
            raise InvalidInputError(f"roundtrip_tol: expected a positive number, got {roundtrip_tol!r}", "roundtrip_tol")
        self.basis = basis
        #: dimension of the flats, of their space, of the triangulation (m - 1)
        self.k, self.d, self.ndim = basis.k, basis.d, basis.m - 1
        self.channels = int(channels)
        self.roundtrip_tol = float(roundtrip_tol)
        if warp is not None and not (
                ((isinstance(warp, LineWarp) and self.k == 1)
                 or (isinstance(warp, FlatWarp) and warp.k == self.k))
                and warp.ndim == self.ndim):
            raise InvalidInputError("warp: expected a flatserve.warp.LineWarp (lines) or "
                                    f"FlatWarp of {self.k}-flats in R^{self.d} on this field "
                                    f"of {self.k}-flats in R^{self.d}", "warp")
        if isinstance(warp, FlatWarp) and not (np.array_equal(warp.Q, basis.Q)
                                               and np.array_equal(warp.r, basis.r)):
            raise InvalidInputError("warp: a FlatWarp calibrated on another chart's basis "
                                    "(FlatWarp.calibrate(basis) of this field's basis)", "warp")
        #: the chart's warp (None: the paper's chart)
        self.warp = warp
        #: tiles of the chart's triangulation (1: one triangulation; "auto": as many as
        #: :func:`flatserve.tiles.auto_tiles` gives, ``triangulation.ntiles`` now)
        self.tiles: int | str = tile_setting(tiles)
        if not 2 <= basis.m - 1 <= MAX_NDIM:  # (the triangulation's bounds, said in k, d)
            raise InvalidInputError(
                f"d: {self.k}-flats in R^{self.d} make {basis.m - 1}-dimensional charts; a "
                f"field's triangulation needs 2 to {MAX_NDIM} dimensions (basis_size(k, d) - 1)",
                "d")
        self._tri = (Triangulation(basis.m - 1) if self.tiles == 1
                     else TiledTriangulation(basis.m - 1, self.tiles))
        self._nrejected = 0
        self._generation = 0
        #: (state, k-d tree, points, values) of the chart the last gradient query saw
        self._tree = None

    @property
    def generation(self) -> int:
        """Inserts since this object was made (a restored field starts at 0): a
        field whose generation is unchanged holds what it held (its snapshot part
        need not be written again)."""
        return self._generation

    # ------------------------------------------------------------------ sizes
    @property
    def nsamples(self) -> int:
        """Distinct samples stored (= vertices of the triangulation)."""
        return self._tri.npoints

    @property
    def nstored(self) -> int:
        """Vertices stored: :attr:`nsamples` (one shard holds each sample once)."""
        return self._tri.npoints

    @property
    def nsimplex(self) -> int:
        return self._tri.nsimplex

    @property
    def nrejected(self) -> int:
        """Total samples rejected by :meth:`add` so far."""
        return self._nrejected

    @property
    def ntiles(self) -> int | None:
        """Tiles of the triangulation now (1 for one triangulation; see ``tiles``)."""
        return self.triangulation.ntiles

    @property
    def points(self) -> np.ndarray:
        """(nsamples, D) embedded coordinates of the samples, in sample-id order."""
        return self._tri.points

    def within(self, x, radius: float) -> np.ndarray:
        """Whether some sample's point lies within ``radius`` of each row of ``x``.

        Parameters
        ----------
        x : (n, D) array_like
            Points in the chart's coordinates (:attr:`points`' space; a
            :meth:`prepare`-d batch's ``x``).
        radius : float
            Euclidean distance there, finite and >= 0 (inclusive).

        Returns
        -------
        (n,) bool
            (:meth:`flatserve.Triangulation.within`.)
        """
        return self._tri.within(x, radius)

    @property
    def values(self) -> np.ndarray:
        """(nsamples, C) values of the samples, in sample-id order."""
        v = self._tri.values
        return np.empty((0, self.channels)) if v is None else v

    @property
    def triangulation(self) -> Triangulation | TiledTriangulation:
        """The Delaunay triangulation of the samples' embedded coordinates (read only;
        over tiles when the field has :attr:`tiles`)."""
        return self._tri

    # ------------------------------------------------------------ charting
    def _flats(self, flats) -> Flats:
        return check_batch(flats, self.k, self.d, "this field holds")

    def chart(self, flats: Flats, *, threads: int | None = None) -> Chart:
        """Express flats in the field's chart: coordinates (Sec. 4) and embedding (Sec. 5).

        Parameters
        ----------
        flats : Flats
            ``n`` k-flats in R^d.
        threads : int, optional
            Threads of the native coordinates kernel; results do not depend on it.

        Returns
        -------
        Chart
            Status per flat and the embedded points of those that round-trip.

        Examples
        --------
        >>> import flatserve
        >>> f = flatserve.Field(flatserve.Basis.around_axis())
        >>> c = f.chart(flatserve.Flats.from_rays([[0, 0, -3.0]], [[0.1, 0, 1.0]]))
        >>> c.points.shape, bool(c.ok[0])
        ((1, 4), True)
        """
        import time

        t0 = time.perf_counter()
        coords = self.basis.coordinates_of(self._flats(flats), self.roundtrip_tol, threads=threads)
        status = np.asarray(coords.status, dtype=np.int8)
        ok = status == OK
        if ok.all():  # no masked copy of the weights
            x = embed(coords.weights) if ok.size else np.empty((0, self.ndim))
        else:
            x = embed(coords.weights[ok]) if ok.any() else np.empty((0, self.ndim))
        if self.warp is not None:
            x = self.warp(x)
        return Chart(status, np.ascontiguousarray(x), np.asarray(coords.residual),
                     time.perf_counter() - t0)

    # --------------------------------------------------------------- writers
    def _prepare(self, flats: Flats, values: np.ndarray, only=None) -> "PreparedBatch":
        # only: this field is its one shard, 0 (checked by prepare)
        if only is not None and 0 not in only:
            raise InvalidInputError("only: a one-chart field is its one shard, 0", "only")
        ch = self.chart(flats)
        ok = ch.ok
        rejected = np.flatnonzero(~ok).astype(np.int64)
        return PreparedBatch(
            nrows=len(ch),
            x=ch.points,
            values=np.ascontiguousarray(values[ok]),
            rejected=rejected,
            reasons=self._reasons(ch, rejected),
        )

    def insert_prepared(self, batch: "PreparedBatch", *,
                        slice_rows: int | None = None) -> AddResult:
        """Second half of :meth:`add`: insert a :meth:`prepare`-d batch (a writer).

        Parameters
        ----------
        batch : PreparedBatch
        slice_rows : int, optional
            Insert at most this many samples at a time: concurrent queries get in
            between slices (each slice is atomic; a query sees the batch in part
            until the last slice is in). Default: the whole batch at once. A
            chart in tiles takes the batch whole whatever ``slice_rows`` (a
            query waits for it) and, when ``slice_rows`` is given, runs the
            batch's exchange under the same write lock (:meth:`settle`): its
            tiles then depend on the batches alone, not on when queries came in
            (replicas applying one log hold the same bytes), and one exchange
            serves the whole batch (an exchange per slice cost the service's
            ingest a third of its time).

        Returns
        -------
        AddResult
        """
        if not isinstance(batch, PreparedBatch) or batch.x.shape[1:] != (self.ndim,) or (
            batch.values.shape[1:] != (self.channels,)
        ):
            raise InvalidInputError("batch: expected a PreparedBatch made by this field", "batch")
        slice_rows = self._slice_rows(slice_rows)
        step = batch.accepted if slice_rows is None or self.tiles != 1 else slice_rows
        duplicates = 0
        # a chart in tiles: the batch whole, with its exchange (under one write lock)
        kw = {"settle": True} if slice_rows is not None and self.tiles != 1 else {}
        for lo in range(0, batch.accepted, max(step, 1)):
            duplicates += int(self._tri.insert(batch.x[lo:lo + step],
                                               batch.values[lo:lo + step], **kw).n_duplicates)
            self._generation += 1
        self._tree = None  # (its arrays and tree are another state's: not kept in memory)
        self._nrejected += int(batch.rejected.size)
        return AddResult(
            accepted=batch.accepted,
            rejected=batch.rejected,
            reasons=batch.reasons,
            duplicates=duplicates,
            nsamples=self.nsamples,
        )

    def add_rays(self, origins, directions, values) -> AddResult:
        """``add(Flats.from_rays(origins, directions), values)``: lines, (n, d) each."""
        return self.add(Flats.from_rays(origins, directions), values)

    def _reasons(self, chart: Chart, rows: np.ndarray) -> list[str]:
        """One human-readable reason per rejected row (``rows`` index the batch)."""
        tol = f"{self.roundtrip_tol:.3g}"
        res = chart.residual[rows].tolist()
        return [
            reason(st)
            + (f" (residual {r:.3g}, tolerance {tol})" if math.isfinite(r) else "")
            for st, r in zip(chart.status[rows].tolist(), res)
        ]

    # --------------------------------------------------------------- readers
    def query(
        self,
        flats: "Flats | Chart",
        *,
        outside: Outside | str = Outside.NAN,
        order: Order | str = Order.HILBERT,
        threads: int | None = None,
        return_weights: bool = False,
        blocking: bool = True,
        interpolant: Interpolant | str = Interpolant.LINEAR,
    ) -> "QueryResult | None":
        """Interpolate the field at flats.

        Parameters
        ----------
        flats : Flats or Chart
            ``q`` k-flats in R^d, or their :meth:`chart` (computed once, e.g.
            to reorder it with :meth:`Chart.take`).
        outside : {"nan", "clamp"}
            Value for queries outside the samples' convex hull; see
            :meth:`flatserve.Triangulation.interpolate`. Queries whose
            coordinates do not round-trip are always NaN and not inside.
        order : {"hilbert", "given"}
            Walk order; "given" keeps the caller's (coherent) order.
        threads : int, optional
            Threads for coordinates and locate/interpolate (default all cores).
        return_weights : bool
            Also return the simplex's sample ids and barycentric weights (taken
            under the same read lock as the values: the same triangulation).
        blocking : bool
            False: return None at once instead of waiting for an insert in
            progress (callers on an event loop).
        interpolant : {"linear", "gradient"}
            "linear" (the paper's): the cell's values, barycentrically weighted.
            "gradient": the cell's vertices' first-order Taylor expansions,
            barycentrically weighted, with slopes fitted to each vertex's
            nearest samples and each expansion limited to the values near its
            vertex (:mod:`flatserve.gradient`), computed under the query's read
            lock from the same state of the chart; queries outside the hull
            keep the linear answer (with ``outside="clamp"`` the answer may
            jump at the hull).

        Returns
        -------
        QueryResult, or None (see ``blocking``)
            ``status`` is the chart's, but ``NO_SAMPLES`` for the flats that
            round-trip while the samples do not span a simplex (an empty field,
            or fewer than ``ndim + 1`` samples in general position): their
            values are NaN, as outside the hull, but the flat is in the domain.
        """
        outside, order = choice(outside, Outside, "outside"), choice(order, Order, "order")
        gradient = choice(interpolant, Interpolant, "interpolant") is Interpolant.GRADIENT
        if gradient:
            _kd_tree()  # (SciPy is there: said before any work)
        ch = flats if isinstance(flats, Chart) else self.chart(flats, threads=threads)
        if ch.points.shape[1:] != (self.ndim,):
            raise InvalidInputError(f"flats: a chart of dimension {self.ndim} expected", "flats")
        n = len(ch)
        ok = ch.ok
        allok = bool(ok.all())
        values = np.full((n, self.channels), np.nan)
        inside = np.zeros(n, dtype=bool)
        ids = weights = None
        if return_weights:
            D = self.ndim
            ids = np.full((n, D + 1), -1, dtype=np.int64)
            weights = np.full((n, D + 1), np.nan)
        if ch.points.shape[0] and self._tri.npoints > 0:
            then = functools.partial(self._taylor, ch.points, threads) if gradient else None
            got = self._tri.query(ch.points, outside=outside, order=order, threads=threads,
                                  locate=return_weights or gradient, blocking=blocking, then=then)
            if got is None:
                return None
            v, ins, loc = got
            if allok:  # no scatter
                values, inside = v, ins
            else:
                values[ok] = v
                inside[ok] = ins
            if return_weights:
                ids[ok] = loc.ids
                weights[ok] = loc.weights
        status = ch.status
        # read after the query: samples are only added, so a triangulation that does
        # not span now did not during the query (all its answers were outside)
        if ok.any() and not inside[ok].all() and not _spans(self._tri, self.ndim):
            status = np.where(ok, np.int8(NO_SAMPLES), status).astype(np.int8)
        return QueryResult(values=values, inside=inside, status=status, ids=ids, weights=weights)

    def _taylor(self, xq: np.ndarray, threads: int | None, v: np.ndarray, inside: np.ndarray,
                loc, held) -> np.ndarray:
        """The gradient interpolant's values where ``inside``: the ``then`` of
        :meth:`query`'s triangulation query, under its read lock (the cells, the
        neighbours and the values of one state of the chart)."""
        if not inside.any():
            return v
        kept = self._tree
        if kept is None or kept[0] != held.state:  # a k-d tree per state of the chart
            points, values = held.arrays()
            kept = (held.state, _kd_tree()(points), points, values)
            self._tree = kept
        _, tree, points, values = kept
        rows = np.flatnonzero(inside)
        # each row's cell vertices in increasing (global) id: the terms are summed in an
        # order that does not depend on how a tile or a cluster listed the cell
        ids, w = loc.ids[rows], loc.weights[rows]
        o = np.argsort(ids, axis=1, kind="stable")
        ids, w = np.take_along_axis(ids, o, axis=1), np.take_along_axis(w, o, axis=1)
        used, at = np.unique(ids, return_inverse=True)
        at = at.reshape(ids.shape)
        # each vertex's slope once per batch; the fits in chunks of vertices and the
        # terms in chunks of rows, so memory grows with the vertices' slopes, not with
        # the batch's rows x (D+1) x C x D (GRADIENT_CHUNK_BYTES)
        step = gradient_chunk(self.ndim, values.shape[1])
        vstep = step * (self.ndim + 1)
        workers = -1 if threads is None else threads
        fits = [slopes(tree, points, values, used[i:i + vstep], workers=workers)
                for i in range(0, used.size, vstep)]
        slope = np.concatenate([f.slope for f in fits])
        low = np.concatenate([f.low for f in fits])
        high = np.concatenate([f.high for f in fits])
        out = v.copy()
        for lo in range(0, rows.size, step):
            part = slice(lo, lo + step)
            ci, ca = ids[part], at[part]
            out[rows[part]] = taylor_blend(points[ci], values[ci], slope[ca], w[part],
                                           xq[rows[part]], low[ca], high[ca])
        return out

    def query_rays(self, origins, directions, **kwargs) -> QueryResult:
        """``query(Flats.from_rays(origins, directions), **kwargs)``: lines, (q, d) each."""
        return self.query(Flats.from_rays(origins, directions), **kwargs)

    # ---------------------------------------------------- the field as shards
    @property
    def shards(self) -> "tuple[Field]":
        """The field's shards: itself (a one-chart field is one shard)."""
        return (self,)

    def route(self, flats: Flats) -> list[np.ndarray]:
        """Per shard, the rows it stores: every row, in the one shard.

        Returns
        -------
        list of one ndarray, shape (n,), int64
        """
        return [np.arange(self._flats(flats).n, dtype=np.int64)]

    def route_query(self, flats: Flats) -> QueryRoute:
        """Per shard, the queries it answers and their weights: all, weight 1."""
        n = self._flats(flats).n
        return QueryRoute(n, [np.arange(n, dtype=np.int64)], [np.ones(n)])

    def blend(self, route: QueryRoute, results: "Sequence[QueryResult | None]", *,
              return_weights: bool = False) -> QueryResult:
        """The field's answer from its shards' answers: the one shard's, as it is."""
        (res,) = results
        if res is None:
            raise InvalidInputError("results: a one-chart field's answer is its shard's",
                                    "results")
        return res

    def copies(self, flats: Flats) -> float:
        """How many shards would store each of these rows on average: 1.0."""
        self._flats(flats)
        return 1.0

    def _definition(self) -> dict:
        return {"atlas": None, "charts": None}

    # ----------------------------------------------------------- persistence
    def _metadata(self) -> dict:
        return {
            "version": self._version,
            "k": self.k,
            "d": self.d,
            "channels": self.channels,
            "roundtrip_tol": self.roundtrip_tol,
            "nrejected": self._nrejected,
            "basis_Q": self.basis.Q.tolist(),
            "basis_r": self.basis.r.tolist(),
            **({"warp": self.warp.to_dict()} if self.warp is not None else {}),
            **({"tiles": self._tri.tiling_dict()} if self.tiles != 1 else {}),
        }

    @property
    def _version(self) -> int:
        if self.tiles != 1:
            return _VERSION_TILES
        return _VERSION if self.warp is None else _VERSION_WARP

    def write_to(self, fh) -> int:
        """Write the field file to an open binary file (the shard's snapshot).

        Layout: 8-byte magic ``FSFIELD\\0``, uint32 version (1; 2 with a
        warp), uint64 metadata length, the metadata as JSON (basis, channels,
        counters, warp), then the native triangulation snapshot (see
        :meth:`flatserve.Triangulation.save`). :meth:`save` writes it to a
        file, :meth:`to_bytes` to bytes, :meth:`from_bytes` reads it.

        Parameters
        ----------
        fh : binary file object
            Written at its current position; not flushed.

        Returns
        -------
        int
            Bytes written.
        """
        head = pack_header(FIELD_MAGIC, self._version, self._metadata())
        payload = self._tri.to_bytes()
        fh.write(head)
        fh.write(payload)
        return len(head) + len(payload)

    def write_parts(self, fh, stage: str | os.PathLike, known: Collection[str] = ()) -> list[str]:
        """Write a snapshot as a small field file plus parts: a field in tiles
        writes one part per tile (its record, :meth:`TiledTriangulation.tile_parts`),
        and only the tiles changed since their part was stored; a field of one
        tile holds its one shard in the field file itself (:meth:`write_to`,
        no parts).

        Parameters
        ----------
        fh : binary file
            Where the field file goes: the header of :meth:`write_to` (version
            3) with ``"parts"``, the tiles' keys in tile order, and no payload.
        stage : path-like
            An existing directory for the new parts (``<stage>/<key>``, fsync'd).
        known : collection of str
            Keys of the parts stored already (not written again).

        Returns
        -------
        list of str
            The keys the field file names (none for one tile).

        Examples
        --------
        >>> import io, tempfile
        >>> f = Field(Basis.around_axis(), tiles=2)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     len(f.write_parts(io.BytesIO(), d))
        2
        """
        if self.tiles == 1:
            return super().write_parts(fh, stage, known)
        got = self._tri.tile_parts(known)
        for key, blob in got:
            if blob is not None:
                write_part(stage, key, blob)
        keys = [key for key, _ in got]
        fh.write(pack_header(FIELD_MAGIC, _VERSION_TILES, {**self._metadata(), "parts": keys}))
        return keys

    @classmethod
    def from_bytes(cls, data, *, source: str = "field", parts=None, only=None) -> "Field":
        """A field from the bytes of a field file (:meth:`write_to`): a shard's restore.

        Parameters
        ----------
        data : bytes-like
            Exactly one field file.
        source : str
            Named in error messages.
        parts : callable, optional
            ``parts(key) -> bytes-like``: a field in tiles written in parts
            (:meth:`write_parts`) reads its tiles' records there, each checked
            against its key; otherwise unused (the file holds the field).
        only : collection of int, optional
            Unused: the one shard is read whatever is asked.

        Raises
        ------
        SnapshotError
            Truncated or damaged data.
        """
        version, meta, start = read_header(data, magic=FIELD_MAGIC,
                                           versions=(_VERSION, _VERSION_WARP, _VERSION_TILES),
                                           kind="field", source=source)
        try:
            basis = Basis(np.array(meta["basis_Q"]), np.array(meta["basis_r"]), int(meta["k"]))
            warp = warp_from_dict(meta["warp"]) if "warp" in meta else None
            if version != _VERSION_TILES and (warp is not None) != (version == _VERSION_WARP):
                raise ValueError(f"version {version} with{'' if warp else 'out'} a warp")
            tiling = meta.get("tiles") if version == _VERSION_TILES else None
            if version == _VERSION_TILES and not isinstance(tiling, dict):
                raise ValueError(f"version {version} without its tiles")
            obj = cls(basis, int(meta["channels"]), roundtrip_tol=float(meta["roundtrip_tol"]),
                      warp=warp, tiles=TiledTriangulation.setting_of(tiling) if tiling else 1)
            keys = meta.get("parts") if tiling else None
            if keys is not None and (not isinstance(keys, list) or len(data) != start):
                raise ValueError("parts: expected a list of keys and no payload")
        except (ValueError, KeyError, TypeError, InvalidInputError) as exc:
            raise corrupted("field", source, exc) from None
        if keys is not None and parts is None:
            raise SnapshotError(f"{source}: its tiles are parts, and no parts were given")
        try:
            if tiling:
                obj._tri = (TiledTriangulation.from_bytes(data[start:], obj.ndim, tiling)
                            if keys is None else
                            TiledTriangulation.from_parts(parts, keys, obj.ndim, tiling,
                                                          source=source))
        except SnapshotError:  # a part missing or damaged: says which itself
            raise
        except (ValueError, KeyError, TypeError, InvalidInputError) as exc:
            raise corrupted("field", source, exc) from None
        if not tiling:
            obj._tri = Triangulation.from_bytes(data[start:])
        if obj._tri.ndim != obj.ndim:
            raise SnapshotError(f"{source}: triangulation dimension {obj._tri.ndim} does not match basis")
        obj._nrejected = int(meta.get("nrejected", 0))
        return obj

    def __repr__(self) -> str:
        return (
            f"Field(k={self.k}, d={self.d}, channels={self.channels}, "
            f"nsamples={self.nsamples}, nsimplex={self.nsimplex}, nrejected={self.nrejected})"
        )
