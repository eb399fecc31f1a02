"""A function sampled on flats over an atlas: one Field per chart, blended.

:class:`AtlasField` is the second kind of field of the contract
:class:`flatserve.contract.SampledField`: a set of *shards*, one
:class:`~flatserve.field.Field` per chart of an :class:`~flatserve.atlas.Atlas`.
Above the shards sit the routing (which charts hold each row: a pure function
of the atlas, :meth:`AtlasField.route`, :meth:`AtlasField.route_query`) and the
blend (the partition of unity that combines the charts' answers,
:meth:`AtlasField.blend`); each chart's insert, query, snapshot and restore are
its Field's own. Every operation over the charts goes through one loop
(``FieldBase._over_shards``), so that running the charts elsewhere (threads,
actors) changes that loop only.

Example
-------
>>> import numpy as np, flatserve
>>> from flatserve.atlas import Atlas
>>> from flatserve.atlas_field import AtlasField
>>> field = AtlasField(Atlas.covering(1, 3), channels=1)   # 16 charts
>>> rng = np.random.default_rng(0)
>>> o, v = rng.normal(size=(3000, 3)), rng.normal(size=(3000, 3))
>>> res = field.add(flatserve.Flats.from_rays(o, v), o[:, 0] ** 2)
>>> res.accepted, len(field.shards)
(3000, 16)
"""
from __future__ import annotations

import contextlib
import math
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Collection, NamedTuple, Sequence

import numpy as np

from ._fieldbase import (FieldBase, corrupted, pack_header, part_key, read_header, read_part,
                         write_part)
from .atlas import (FIT_MAX_DIM, MAX_UNIT, MIN_UNIT, UNIT_RULES, Atlas, data_unit,
                    default_unit_rule)
from .coordinates import NO_SAMPLES, NOT_REPRESENTABLE, OK, ROUNDTRIP_TOL
from .errors import InvalidInputError, SnapshotError
from .field import AddResult, Field, PreparedBatch, QueryResult, QueryRoute
from .flats import Flats, basis_size
from .grassmann import bump
from .options import Interpolant, Order, Outside, choice
from .triangulation import RWLock, seam_net

__all__ = ["ATLAS_MAGIC", "AtlasField", "AtlasPrepared", "AtlasQueryResult", "FIT_FACTORS",
           "FIT_MAX_DIM", "FIT_MIN_ROWS", "FittedUnit", "choose_unit", "default_unit_rule",
           "fit_max_rows", "fitted_unit"]

ATLAS_MAGIC = b"FSATLAS\x00"
_VERSION = 1
#: The version of an atlas field file whose charts are parts, named by key
#: (:meth:`AtlasField.write_parts`); both are read.
_VERSION_PARTS = 2
_LENGTH = struct.Struct("<Q")  # the length of each chart's field file
_NO_ROWS = np.empty(0, np.int64)
_NO_ROWS.setflags(write=False)


@dataclass(frozen=True)
class AtlasPrepared:
    """A batch routed and charted by :meth:`AtlasField.prepare`, not yet inserted:
    each chart's :class:`~flatserve.field.PreparedBatch` parts.

    ``parts[i]`` is None when chart ``i`` holds no accepted row of the
    ``nrows``, else the triple ``(own, shared, outer)`` its Field's ``prepare``
    made: the rows whose nearest centre is this chart's, those nearer to
    another centre (the overlap: inserted so that the chart covers its
    blending domain), and of those the ones beyond the atlas's
    ``dense_reach`` (empty without it), which :meth:`AtlasField.insert_prepared`
    inserts only while the chart is sparse (``dense_after``) and where its net
    has room (``seam_spacing``): ``rows[i]`` is the triple of the parts' rows
    in the batch (int64, increasing), which says what came before each.
    ``accepted_rows`` (int64) were accepted by at least one chart; ``rejected``
    (int64) by none, one of ``reasons`` each (the first chart's).
    """

    nrows: int
    parts: tuple
    accepted_rows: np.ndarray
    rejected: np.ndarray
    reasons: list
    #: the atlas's unit of length the batch was charted in (:meth:`AtlasField.insert_prepared`
    #: refuses it in a field whose unit has changed since: a unit chosen from the data)
    unit: float = 1.0
    rows: tuple = ()

    @property
    def accepted(self) -> int:
        return int(self.accepted_rows.size)


@dataclass(frozen=True)
class AtlasQueryResult(QueryResult):
    """:class:`~flatserve.field.QueryResult` of an :class:`AtlasField`.

    ``values`` is the blend ``sum_i w_i v_i`` over the charts whose domain
    holds the query (partition-of-unity weights ``w_i``).  With
    ``return_weights``, ``ids``/``weights`` have shape (q, P, D+1): per
    contributing chart (``charts`` (q, P), -1 for none) the chart's sample
    ids and its barycentric weights times ``w_i``, so that
    ``values[q] = sum_{p, v} weights[q, p, v] * chart_values[charts[q, p]][ids[q, p, v]]``.
    """

    charts: np.ndarray | None = None


def _slices(parts, step: int) -> list[list]:
    """``(chart, PreparedBatch, own)`` parts cut into groups of at most ``step``
    samples over all charts, in order (a part larger than ``step`` is cut)."""
    groups: list[list] = []
    cur: list = []
    n = 0
    for c, p, own in parts:
        for lo in range(0, p.accepted, step):
            size = min(step, p.accepted - lo)
            piece = p if size == p.accepted else PreparedBatch(
                size, p.x[lo:lo + step], p.values[lo:lo + step], _NO_ROWS, [])
            if cur and n + size > step:
                groups.append(cur)
                cur, n = [], 0
            cur.append((c, piece, own))
            n += size
    if cur:
        groups.append(cur)
    return groups


def _by_shard(group) -> list[tuple[int, list]]:
    """``(chart, part, own)`` triples (in chart order) as ``(chart, [(part, own), ...])``:
    each chart once, its parts in their order."""
    out: list[tuple[int, list]] = []
    for c, p, own in group:
        if not out or out[-1][0] != c:
            out.append((c, []))
        out[-1][1].append((p, own))
    return out


class AtlasField(FieldBase):
    """Values sampled on k-flats, over an :class:`~flatserve.atlas.Atlas`: one Field per chart, blended.

    Every sample is inserted into each chart whose centre is closer than
    ``atlas.reach``; a query is answered by every chart whose centre is
    closer than ``atlas.trusted``, and the answers are blended with the
    partition of unity ``w_i = bump(angle_i) / sum_j bump(angle_j)``
    (:func:`flatserve.grassmann.bump`), which varies continuously (C^2) with
    the query flat: the interpolant has no seam where one chart hands over to
    the next.  Charts whose answer is missing (outside their samples' hull)
    are left out of the sum.  Deep inside a chart (no other centre closer
    than ``trusted``) the answer is that chart's :class:`~flatserve.field.Field`'s.

    Thread safety as :class:`~flatserve.field.Field`: readers together, a
    writer alone.  The field's own readers/writer lock makes a batch atomic
    across charts: :meth:`query` and :meth:`save` see a whole
    :meth:`insert_prepared` batch in every chart, or in none.

    Parameters
    ----------
    atlas : Atlas
    channels : int
    roundtrip_tol : float
        Of every chart's Field.

    Attributes
    ----------
    atlas : Atlas
    fields : list of Field
        One per chart, in chart order (:attr:`shards` is the same as a tuple).
    """

    #: answers blend several charts: ids / weights are (q, P, D+1)
    blends = True

    def __init__(self, atlas: Atlas, channels: int = 1, *,
                 roundtrip_tol: float = ROUNDTRIP_TOL):
        if not isinstance(atlas, Atlas):
            raise InvalidInputError(f"atlas: expected a flatserve.atlas.Atlas, got "
                                    f"{type(atlas).__name__}", "atlas")
        self.atlas = atlas
        #: the definition leaves the unit to the data (the atlas's unit is None) and no
        #: batch was inserted yet: the field may take a unit (settle_unit)
        self._chooses_unit = atlas.unit_from_data
        self.fields = [atlas.chart_field(i, channels, roundtrip_tol=roundtrip_tol)
                       for i in range(atlas.ncharts)]
        self.k, self.d, self.ndim = atlas.k, atlas.d, self.fields[0].ndim
        self.channels = self.fields[0].channels
        self.roundtrip_tol = self.fields[0].roundtrip_tol
        self._nsamples = 0
        self._nrejected = 0
        #: per chart, the distinct samples it holds as their nearest chart (a sample
        #: counts once, in its nearest chart): ``nsamples`` is their sum; None when
        #: restored from a file that did not record them
        self._own: list[int] | None = [0] * len(self.fields)
        self._lock = RWLock()
        #: writers one batch at a time, whole (its slices let readers in, not another
        #: writer): a thinner seam's decisions count the samples of the batches before
        self._writing = threading.Lock()
        #: per chart, (its generation, the key of its part) when a part was last
        #: written or read: unchanged since, it need not be made again
        self._parts: list[tuple[int, str] | None] = [None] * len(self.fields)

    # ------------------------------------------------------------------ sizes
    @property
    def nsamples(self) -> int:
        """Distinct samples (each counted in its nearest chart)."""
        return self._nsamples

    @property
    def nstored(self) -> int:
        """Vertices over all charts (a sample counts once per chart holding it)."""
        return int(sum(f.nsamples for f in self.fields))

    @property
    def duplication(self) -> float:
        """``nstored / nsamples``: how many charts hold a sample on average."""
        return self.nstored / self._nsamples if self._nsamples else float("nan")

    @property
    def nsimplex(self) -> int:
        """Cells over all charts' triangulations."""
        return int(sum(f.nsimplex for f in self.fields))

    @property
    def samples_per_chart(self) -> list[int]:
        return [f.nsamples for f in self.fields]

    @property
    def nrejected(self) -> int:
        return self._nrejected

    # ---------------------------------------------------- a unit from the data
    @property
    def unit_pending(self) -> bool:
        """The atlas's unit is still to be chosen from the first samples (``Atlas(...,
        unit=None)``): :meth:`prepare` of the first batch chooses it (:meth:`settle_unit`)."""
        return self.atlas.unit_from_data

    @property
    def unit(self) -> float | None:
        """The charts' unit of length (the atlas's); None while it is still to be
        chosen (:attr:`unit_pending`)."""
        return None if self.unit_pending else self.atlas.unit

    @property
    def unit_from_data(self) -> bool:
        """The field may still take a unit (:meth:`settle_unit`): its definition leaves
        the unit to its first samples (``Atlas(unit=None)``) and no batch has been
        inserted yet (the first insert fixes the unit, even with no row for this
        field's charts: the unit of the batch first in the log). False for a
        definition that states the unit (an import of a field that chose it)."""
        return self._chooses_unit

    def settle_unit(self, unit: float, *, if_empty: bool = False) -> bool:
        """Adopt ``unit`` as the charts' unit of length while the field holds no samples.

        For a field whose unit is chosen from the data and that has inserted no
        batch yet (:attr:`unit_from_data`): its charts are rebuilt in ``unit``
        (:meth:`flatserve.atlas.Atlas.with_unit`), empty. Asking for the unit it
        has is a no-op. A writer (the field's write lock).

        Parameters
        ----------
        unit : float
            Positive: e.g. :func:`flatserve.atlas.data_unit` of the first batch, or
            the unit recorded with it (a replica, a restart).
        if_empty : bool
            A field that can no longer take a unit keeps its own and returns False,
            whatever ``unit`` (a writer that checked before a batch got in).

        Returns
        -------
        bool
            Whether the charts were rebuilt.

        Raises
        ------
        InvalidInputError
            (Not ``if_empty``.) The field's unit was given at its creation, or was
            chosen from its first batch, which it has inserted.
        """
        with self._lock.write():
            if not self.atlas.unit_from_data and float(unit) == self.atlas.unit:
                return False
            if not self._chooses_unit or self._nsamples or self._nrejected:
                if if_empty:
                    return False
                if self.atlas.info.get("unit_from") in UNIT_RULES:
                    raise InvalidInputError(f"unit: the field's unit {self.atlas.unit:g} was "
                                            f"chosen from its first batch, which it holds; "
                                            f"{float(unit):g} cannot replace it", "unit")
                raise InvalidInputError(f"unit: the field's unit ({self.atlas.unit:g}) was "
                                        "given when it was created", "unit")
            atlas = self.atlas.with_unit(unit)
            self.fields = [atlas.chart_field(i, self.channels, roundtrip_tol=self.roundtrip_tol)
                           for i in range(atlas.ncharts)]
            self.atlas = atlas
            self._parts = [None] * len(self.fields)
            return True

    def in_unit(self, unit: float) -> "AtlasField":
        """This field, or an empty one of the same definition in another unit of length.

        What a writer charts a batch with when the batch's own unit may become the
        field's (:func:`flatserve.atlas.data_unit` of the batch, before the field
        has taken a unit from the batch first in its log): ``self`` when ``unit``
        is its unit, else a new empty field over ``atlas.with_unit(unit)`` whose
        prepared batches carry that unit (:attr:`AtlasPrepared.unit`: this field
        refuses them unless it takes the unit). Reads the definition only.
        """
        if not self.atlas.unit_from_data and float(unit) == self.atlas.unit:
            return self
        other = AtlasField(self.atlas.with_unit(unit), self.channels,
                           roundtrip_tol=self.roundtrip_tol)
        return other

    # ---------------------------------------------------- the field as shards
    @property
    def shards(self) -> tuple[Field, ...]:
        """The charts' fields, in chart order."""
        return tuple(self.fields)

    def route(self, flats: Flats) -> list[np.ndarray]:
        """Per chart, the rows it may store: those closer than ``atlas.reach`` to its centre.

        A pure function of the atlas (a row's charts do not depend on its
        batch); with a ``dense_reach``, a chart stores a row beyond it only while
        sparse (``dense_after``) and where its net has room (``seam_spacing``:
        :meth:`insert_prepared`).

        Returns
        -------
        list of ndarray (int64)
            One per chart, increasing row indices.
        """
        return self.atlas.route(flats, self.atlas.reach, nearest=False).rows

    def copies(self, flats: Flats, *, own: Sequence[int | None] | None = None) -> float:
        """How many charts would store each of these rows on average, now.

        ``sum(len(r) for r in route(flats)) / n`` (before round-trip
        rejections; 0.0 for no rows), counted without the angles
        (:meth:`flatserve.atlas.Atlas.held`); with a ``dense_reach``, the charts
        that are dense already count the rows within it only (an estimate: the
        charts' own samples are read without waiting for a writer).

        Parameters
        ----------
        flats : Flats
        own : sequence of (int or None), optional
            Per chart, its own samples (None: not known, sparse) instead of this
            field's: a field whose charts are held elsewhere
            (:class:`flatserve.service.cluster.front.remote.RemoteField`).
        """
        at = self.atlas
        n = at.check_flats(flats).n
        if not n:
            return 0.0
        if at.dense_reach is None:
            return float(at.held(flats, at.reach).sum()) / n
        ro = at.route(flats, at.reach)  # (one routing: a dense chart's rows are a subset)
        held = sum(r.size if sparse else r.size - int(at.beyond_dense(ro, c).sum())
                   for c, (r, sparse) in enumerate(zip(ro.rows, self._sparse(own))))
        return float(held) / n

    def _outer_kept(self, c: int, f, three: tuple, rows: tuple) -> tuple:
        """Chart ``c``'s ``(own, shared, outer)`` parts of a batch (its Field ``f``)
        with ``outer`` cut to the rows before which the chart holds fewer than
        ``dense_after`` own samples, and of those (``seam_spacing``) to the ones
        that no sample it holds, no row of ``own`` or ``shared`` before it and no
        kept ``outer`` row before it lies within ``seam_spacing`` of in the chart's
        coordinates at scale 1 (:func:`flatserve.triangulation.seam_net`). Depends on the
        samples before each row, not on how they were cut into batches or slices
        (:meth:`insert_prepared`; under the writer mutex: the chart does not change)."""
        own, shared, outer = three
        at = self.atlas
        if not outer.accepted or at.dense_reach is None:
            return three
        r_own, r_shared, r_outer = rows
        keep = np.ones(outer.accepted, dtype=bool)
        if at.dense_after is not None and self._own is not None:
            keep = self._own[c] + np.searchsorted(r_own, r_outer) < at.dense_after
        if at.seam_spacing is not None and keep.any():
            idx = np.flatnonzero(keep)
            x = np.ascontiguousarray(outer.x[idx])
            base_at = np.concatenate([r_own, r_shared])
            order = np.argsort(base_at, kind="stable")
            base = np.concatenate([own.x, shared.x])[order]
            radius = at.seam_spacing / float(at.scales[c])  # (points scale as 1 / scale)
            keep[idx] = seam_net(x, r_outer[idx], base, base_at[order], radius,
                                 f.within(x, radius))
        if keep.all():
            return three
        return own, shared, PreparedBatch(int(keep.sum()), outer.x[keep], outer.values[keep],
                                          _NO_ROWS, [])

    def _sparse(self, own: Sequence[int | None] | None = None) -> list[bool]:
        """Per chart, whether it still stores its seam beyond ``dense_reach`` (fewer
        than ``dense_after`` own samples; every chart without a ``dense_after``, or
        whose own samples are not known: a field read from an older file). ``own``:
        per chart its own samples (None: not known) instead of this field's."""
        at = self.atlas
        own = self._own if own is None else own
        if at.dense_after is None or own is None:
            return [True] * len(self.fields)
        return [o is None or o < at.dense_after for o in list(own)]

    def route_query(self, flats: Flats) -> QueryRoute:
        """Per chart, the queries closer than ``atlas.trusted`` to its centre, and
        their blending weights ``bump(angle)`` (:func:`flatserve.grassmann.bump`);
        a relative atlas's: :meth:`flatserve.atlas.Atlas.relative_weights`."""
        at = self.atlas
        if at.relative:
            ro = at.route(flats, at.trusted, nearest=True)
            return QueryRoute(flats.n, ro.rows, at.relative_weights(ro))
        ro = at.route(flats, at.trusted, nearest=False)
        inner, trusted = math.radians(at.inner), math.radians(at.trusted)
        return QueryRoute(flats.n, ro.rows, [bump(a, inner, trusted) for a in ro.angles])

    def blend(self, route: QueryRoute, results: Sequence[QueryResult | None], *,
              return_weights: bool = False) -> AtlasQueryResult:
        """The field's answer from its charts' answers: the partition of unity.

        ``values[q] = sum_i w_i v_i / sum_i w_i`` over the charts ``i`` whose
        answer at ``q`` is finite, ``w_i`` the route's weights; the sums of a
        row are added in increasing chart order, from 0.0 (the same bits
        whatever the batch).

        Parameters
        ----------
        route : QueryRoute
            Of :meth:`route_query`.
        results : sequence of QueryResult or None
            Per chart its Field's answer on ``route.rows[i]``; None: the chart
            holds no samples (or routes no rows), so its rows are
            ``NO_SAMPLES`` unless another chart answers them.
        return_weights : bool
            The results carry ids and weights: return them per chart
            (:class:`AtlasQueryResult`).

        Returns
        -------
        AtlasQueryResult
            ``status`` per row: ``OK`` where some chart that holds it answered
            ``OK``; else ``NO_SAMPLES`` where some chart holds it (routes it)
            but its samples do not span a simplex; else ``NOT_REPRESENTABLE``.
        """
        n, C = route.n, self.channels
        num = np.zeros((n, C))
        den = np.zeros(n)
        inside = np.zeros(n, dtype=bool)
        status = np.full(n, NOT_REPRESENTABLE, dtype=np.int8)
        if return_weights:
            counts = np.bincount(np.concatenate(route.rows), minlength=n) if n else np.zeros(0, int)
            P = int(counts.max(initial=0))
            D1 = self.ndim + 1
            ids = np.full((n, P, D1), -1, dtype=np.int64)
            wts = np.zeros((n, P, D1))
            charts = np.full((n, P), -1, dtype=np.int64)
            blend = np.zeros((n, P))
            slot = np.zeros(n, dtype=np.int64)
        okm = np.zeros(n, dtype=bool)
        empty = np.zeros(n, dtype=bool)
        for c, res in enumerate(results):
            if res is None:
                empty[route.rows[c]] = True
                continue
            rows, b = route.rows[c], route.weights[c]
            v = res.values
            fin = np.isfinite(v)
            good = fin[:, 0] if C == 1 else fin.all(axis=1)
            w = b if good.all() else np.where(good, b, 0.0)  # the common case: no masking
            if C == 1:  # 1-D scatters (much faster than (m, 1) ones)
                num[:, 0][rows] += w * (v[:, 0] if w is b else np.where(good, v[:, 0], 0.0))
            else:
                num[rows] += w[:, None] * (v if w is b else np.where(good[:, None], v, 0.0))
            den[rows] += w
            inside[rows] |= res.inside & (w > 0)
            okm[rows[res.status == OK]] = True
            empty[rows[res.status == NO_SAMPLES]] = True
            if return_weights:
                s = slot[rows]
                ids[rows, s] = res.ids
                wts[rows, s] = np.where(good[:, None], res.weights, 0.0)
                charts[rows, s] = c
                blend[rows, s] = w
                slot[rows] += 1
        status[empty] = NO_SAMPLES
        status[okm] = OK
        has = den > 0
        values = np.full((n, C), np.nan)
        np.divide(num, den[:, None], out=values, where=has[:, None])
        if return_weights:
            with np.errstate(invalid="ignore", divide="ignore"):
                wts *= (blend / np.where(has, den, np.nan)[:, None])[:, :, None]
            wts[~has] = np.nan
            return AtlasQueryResult(values, inside, status, ids, wts, charts)
        return AtlasQueryResult(values, inside, status)

    # --------------------------------------------------------------- writers
    def _flats(self, flats: Flats) -> Flats:
        return self.atlas.check_flats(flats)

    def _prepare(self, flats: Flats, values: np.ndarray, only=None) -> AtlasPrepared:
        # route to the charts whose domain (reach) holds each row; each chart
        # charts its rows (its Field's prepare), split into its own and shared.
        # A unit still to be chosen is chosen here, from this (the first) batch.
        n = flats.n
        if self.atlas.unit_from_data and n:
            self.settle_unit(choose_unit(self.atlas, flats, values))
        unit = self.atlas.unit
        ro = self.atlas.route(flats, self.atlas.reach)
        work = [(c, rows) for c, rows in enumerate(ro.rows)
                if rows.size and (only is None or c in only)]
        prepared = self._over_shards(lambda f, rows: f.prepare(flats.take(rows), values[rows]),
                                     work)
        taken = np.zeros(n, dtype=bool)
        first_reason: dict[int, str] = {}
        parts: list = [None] * len(self.fields)
        part_rows: list = [None] * len(self.fields)
        for (c, rows), pb in zip(work, prepared):
            okm = np.ones(rows.size, dtype=bool)
            okm[pb.rejected] = False
            for i, why in zip(pb.rejected.tolist(), pb.reasons):
                first_reason.setdefault(int(rows[i]), f"chart {c}: {why}")
            acc = rows[okm]
            taken[acc] = True
            mine = ro.nearest[acc] == c
            # the seam beyond dense_reach: stored only while the chart is sparse
            outer = self.atlas.beyond_dense(ro, c)[okm]
            parts[c] = tuple(PreparedBatch(int(m.sum()), pb.x[m], pb.values[m], _NO_ROWS, [])
                             for m in (mine, ~mine & ~outer, outer))
            part_rows[c] = tuple(acc[m].astype(np.int64) for m in (mine, ~mine & ~outer, outer))
        if only is not None:  # the decisions of the charts not asked are unknown: only the
            # rows no chart's domain holds are known to be rejected
            held = np.zeros(n, dtype=bool)
            for rows in ro.rows:
                held[rows] = True
            taken |= held
        rejected = np.flatnonzero(~taken).astype(np.int64)
        reach = self.atlas.reach
        reasons = [first_reason.get(int(i), (
            f"outside every chart's domain: {math.degrees(ro.nearest_angle[i]):.2f} degrees "
            f"from the nearest centre (chart {int(ro.nearest[i])}), charts reach {reach:g}"))
            for i in rejected.tolist()]
        return AtlasPrepared(n, tuple(parts), np.flatnonzero(taken).astype(np.int64), rejected,
                             reasons, unit, tuple(part_rows))

    def insert_prepared(self, batch: AtlasPrepared, *,
                        slice_rows: int | None = None) -> AddResult:
        """Insert a :meth:`prepare`-d batch into its charts (a writer).

        Each chart's parts go to that chart's :meth:`Field.insert_prepared`; of a
        chart's ``outer`` part (its seam beyond the atlas's ``dense_reach``) the
        rows before which the chart holds fewer than ``dense_after`` own samples
        (those it held at the batch's start and its own rows of the batch before
        the row), and of those, with a ``seam_spacing``, the ones no sample before
        them covers (:meth:`_outer_kept`): which charts store a sample depends on the samples before it,
        not on how they were cut into batches or slices (but for duplicates), so
        a log replayed in order stores each sample where it was stored first.

        Parameters
        ----------
        batch : AtlasPrepared
        slice_rows : int, optional
            As :meth:`Field.insert_prepared`: insert at most this many samples
            (counted over the charts) at a time, so that concurrent queries get in
            between slices. Each slice is atomic: a batch holding at most
            ``slice_rows`` samples over all its charts is seen in every chart or in
            none; a larger one is seen in part (some charts, or part of a chart)
            until its last slice is in. Default: the whole batch at once.

        Returns
        -------
        AddResult
            ``duplicates`` counts rows that coincided with a sample already in
            their nearest chart; ``nsamples`` the distinct samples afterwards.
        """
        if not isinstance(batch, AtlasPrepared) or len(batch.parts) != len(self.fields) \
                or len(batch.rows) != len(self.fields):
            raise InvalidInputError("batch: expected an AtlasPrepared made by this field",
                                    "batch")
        slice_rows = self._slice_rows(slice_rows)
        with self._writing:  # one writer's batch at a time
            with self._lock.write():  # (settle_unit takes it too)
                if batch.accepted and self.atlas.unit_from_data:
                    raise InvalidInputError(f"batch: charted in the unit {batch.unit:g}; the "
                                            "field has not taken a unit yet (settle_unit)",
                                            "batch")
                if batch.accepted and batch.unit != self.atlas.unit:
                    raise InvalidInputError(f"batch: charted in the unit {batch.unit:g}, the "
                                            f"field's is {self.atlas.unit:g} (chosen since): "
                                            "prepare it again", "batch")
                if not self.atlas.unit_from_data:
                    self._chooses_unit = False  # the first batch inserted fixes the unit
            # what each chart keeps of its outer seam: read from the charts as they are
            # (no other writer while this one holds the mutex), readers still in
            work = [(c, (c, three, batch.rows[c])) for c, three in enumerate(batch.parts)
                    if three is not None]
            kept = self._over_shards(lambda f, item: self._outer_kept(item[0], f, *item[1:]),
                                     work)
            parts = [(c, p, own) for (c, _), three in zip(work, list(kept))
                     for p, own in zip(three, (True, False, False)) if p.accepted]
            groups = [parts] if slice_rows is None or not parts else _slices(parts, slice_rows)
            duplicates = 0
            for i, group in enumerate(groups):
                with self._lock.write():  # a whole batch, or one slice
                    work = _by_shard(group)
                    done = self._over_shards(
                        lambda f, ps: [(f.insert_prepared(p), own) for p, own in ps], work)
                    for (c, _), rs in zip(work, list(done)):
                        for res, own in rs:
                            if own:  # a sample counts once, in its nearest chart
                                duplicates += res.duplicates
                                self._nsamples += res.accepted - res.duplicates
                                if self._own is not None:
                                    self._own[c] += res.accepted - res.duplicates
                    if i == len(groups) - 1:
                        self._nrejected += int(batch.rejected.size)
            return AddResult(accepted=batch.accepted, rejected=batch.rejected,
                             reasons=batch.reasons, duplicates=duplicates,
                             nsamples=self._nsamples)

    # --------------------------------------------------------------- readers
    def query(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
              order: Order | str = Order.HILBERT,
              threads: int | None = None, return_weights: bool = False,
              blocking: bool = True,
              interpolant: Interpolant | str = Interpolant.LINEAR) -> "AtlasQueryResult | None":
        """Interpolate at flats: every chart holding the query, blended.

        :meth:`route_query`, each chart's :meth:`Field.query` on its rows,
        :meth:`blend`.

        Parameters
        ----------
        flats : Flats
            ``q`` k-flats in R^d.
        outside, order, threads
            Passed to each chart's :meth:`Field.query`.
        return_weights : bool
            Also return per contributing chart the sample ids and weights
            (:class:`AtlasQueryResult`).
        blocking : bool
            False: return None at once instead of waiting for an insert in progress.
        interpolant : {"linear", "gradient"}
            Each chart's (:meth:`Field.query`).

        Returns
        -------
        AtlasQueryResult
            ``status`` is OK when some chart's coordinates round-trip and its
            samples span a simplex; ``NO_SAMPLES`` when charts hold the query
            but none of them has samples that span one (an empty field, or
            empty charts); ``NOT_REPRESENTABLE`` when no chart's domain holds
            the query.
            ``inside`` when some chart with positive weight answered from
            inside its samples' hull.
        """
        outside, order = choice(outside, Outside, "outside"), choice(order, Order, "order")
        interpolant = choice(interpolant, Interpolant, "interpolant")
        route = self.route_query(flats)
        if blocking:
            self._lock.acquire_read()
        elif not self._lock.try_acquire_read():
            return None
        try:  # charts change only under this lock's write side: they never make us wait
            work = [(c, flats.take(rows)) for c, rows in enumerate(route.rows)
                    if rows.size and self.fields[c].nsamples]
            got = self._query_shards(work, outside=outside, order=order, threads=threads,
                                     return_weights=return_weights, interpolant=interpolant)
            results: list = [None] * len(self.fields)
            for (c, _), res in zip(work, got):
                results[c] = res
            return self.blend(route, results, return_weights=return_weights)
        finally:
            self._lock.release_read()

    def query_shards(self, work, *, outside: Outside | str = Outside.NAN,
                     order: Order | str = Order.HILBERT, threads: int | None = None,
                     return_weights: bool = False, blocking: bool = True,
                     interpolant: Interpolant | str = Interpolant.LINEAR) -> list | None:
        """Each chart's answer on its own flats, seen at one moment (a shard's half of
        :meth:`query`: :meth:`route_query` and :meth:`blend` are the other).

        Parameters
        ----------
        work : list of (int, Flats)
            ``(chart, flats)`` pairs, each chart at most once.
        outside, order, threads, return_weights, blocking, interpolant
            As :meth:`query`.

        Returns
        -------
        list of QueryResult or None
            Per pair, its chart's :meth:`Field.query`; None for a chart that holds
            no samples. None (the whole answer) when not ``blocking`` and a writer
            is in. Under the field's read lock: every chart holds the same batches.
        """
        outside, order = choice(outside, Outside, "outside"), choice(order, Order, "order")
        interpolant = choice(interpolant, Interpolant, "interpolant")
        if blocking:
            self._lock.acquire_read()
        elif not self._lock.try_acquire_read():
            return None
        try:
            asked = [(c, f) for c, f in work if self.fields[c].nsamples]
            got = iter(self._query_shards(asked, outside=outside, order=order, threads=threads,
                                          return_weights=return_weights,
                                          interpolant=interpolant))
            return [next(got) if self.fields[c].nsamples else None for c, _ in work]
        finally:
            self._lock.release_read()

    def _query_shards(self, work, **kw) -> list:
        return list(self._over_shards(lambda f, flats: f.query(flats, **kw), work))

    def _definition(self) -> dict:
        out = self.atlas.describe_spec(self.atlas.to_dict())
        for chart, f in zip(out["charts"], self.fields):
            chart["samples"] = f.nsamples
        return out

    # ----------------------------------------------------------- persistence
    def write_to(self, fh) -> int:
        """Write the field file to an open binary file (a snapshot of every chart).

        Layout: 8-byte magic ``FSATLAS\\0``, uint32 version, uint64 metadata
        length, the metadata JSON (``{"atlas": Atlas.to_dict(), "channels",
        "roundtrip_tol", "nsamples", "nrejected", "charts": c}``), then per
        chart a uint64 length and that chart's field file
        (:meth:`Field.write_to`, its own snapshot).  A reader: may run beside
        queries; a batch inserted meanwhile waits (the snapshot holds whole
        batches).

        Returns
        -------
        int
            Bytes written.
        """
        with self._lock.read():
            head = pack_header(ATLAS_MAGIC, _VERSION, self._meta())
            fh.write(head)
            size = len(head)
            blobs = self._over_shards(lambda f, _: f.to_bytes(),
                                      [(c, None) for c in range(len(self.fields))])
            with contextlib.closing(blobs):  # a failed write: no chart serialised on after it
                for blob in blobs:
                    fh.write(_LENGTH.pack(len(blob)))
                    fh.write(blob)
                    size += _LENGTH.size + len(blob)
        return size

    def _meta(self) -> dict:
        return {"atlas": self.atlas.to_dict(), "channels": self.channels,
                "roundtrip_tol": self.roundtrip_tol, "nsamples": self._nsamples,
                "nrejected": self._nrejected, "charts": len(self.fields),
                **({"own": list(self._own)} if self._own is not None else {}),
                **({"chooses_unit": True} if self._chooses_unit else {})}

    def write_parts(self, fh, stage, known=()) -> list[str]:
        """Write a snapshot as a small field file plus one part per chart,
        writing only the parts of the charts that changed.

        A chart's part is its field file (:meth:`Field.write_to`), named by
        its key (:func:`~flatserve._fieldbase.part_key`). A chart unchanged
        since its part was last written or read (its
        :attr:`Field.generation`), whose key is in ``known``, is not even
        serialised; a changed one is written to ``<stage>/<key>`` (fsync'd)
        unless its key is known. The field file written to ``fh`` is the
        header of :meth:`write_to` (version 2) with ``"parts"``: the keys, in
        chart order. The charts run on the shard pool. A reader, like
        :meth:`write_to`.

        Parameters
        ----------
        fh : binary file
        stage : path-like
            An existing directory for the new parts.
        known : collection of str
            Keys of the parts stored already.

        Returns
        -------
        list of str
            The keys of every chart's part, in chart order.

        Examples
        --------
        >>> import tempfile, io
        >>> f = AtlasField(Atlas.covering(1, 3), channels=1)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     keys = f.write_parts(io.BytesIO(), d)
        ...     len(keys) == f.atlas.ncharts
        True
        """
        known = frozenset(known)
        stage = Path(stage)

        def part(f: Field, c: int) -> str:
            key, blob = self._chart_part(f, c, known)
            if blob is not None:
                write_part(stage, key, blob)
            return key

        with self._lock.read():
            keys = list(self._over_shards(part, [(c, c) for c in range(len(self.fields))]))
            fh.write(pack_header(ATLAS_MAGIC, _VERSION_PARTS, {**self._meta(), "parts": keys}))
        return keys

    def _chart_part(self, f: Field, c: int, known: frozenset) -> tuple[str, bytes | None]:
        """Chart ``c``'s part: its key, and its bytes unless the key is ``known``
        (an unchanged chart whose part is known is not even serialised)."""
        gen, last = f.generation, self._parts[c]
        if last is not None and last[0] == gen and last[1] in known:
            return last[1], None
        blob = f.to_bytes()
        key = part_key(blob)
        self._parts[c] = (gen, key)  # each chart is one thread's in a call
        return key, None if key in known else blob

    def chart_parts(self, charts: Sequence[int], known: Collection[str] = ()) -> list:
        """The parts of some charts, for a snapshot assembled elsewhere (a shard
        held in another process: :meth:`write_parts` there names them).

        Parameters
        ----------
        charts : sequence of int
        known : collection of str
            Keys of the parts stored already (their bytes are not returned).

        Returns
        -------
        list of (int, str, bytes or None)
            Per chart, its index, its part's key, and the part's bytes (None
            when the key is known). A reader, like :meth:`write_parts`.
        """
        known = frozenset(known)
        with self._lock.read():
            got = self._over_shards(lambda f, c: (c, *self._chart_part(f, c, known)),
                                    [(c, c) for c in charts])
            return list(got)

    def parts_header(self, keys: Sequence[str], *, own: Sequence[int], nrejected: int,
                     unit_fixed: bool = False) -> bytes:
        """The field file of a snapshot in parts whose charts were serialised
        elsewhere (:meth:`chart_parts` of the processes holding them): this
        field's definition with those charts' ``keys``, ``own`` samples and the
        field's ``nrejected``; read back by :meth:`from_bytes` with the parts.
        ``unit_fixed``: the snapshot is taken after a batch (its unit, if chosen
        from the data, is fixed, whatever this field, which may hold none of
        the batches, would still take)."""
        own = [int(x) for x in own]
        if len(keys) != len(self.fields) or len(own) != len(self.fields):
            raise InvalidInputError(f"keys, own: expected one per chart ({len(self.fields)})",
                                    "keys")
        meta = {**self._meta(), "nsamples": sum(own), "nrejected": int(nrejected), "own": own,
                "parts": list(keys)}
        if unit_fixed:
            meta.pop("chooses_unit", None)
        return pack_header(ATLAS_MAGIC, _VERSION_PARTS, meta)

    @property
    def own_samples(self) -> list[int] | None:
        """Per chart, the distinct samples whose nearest chart it is (their sum is
        :attr:`nsamples`); None for a field read from a file that did not
        record them."""
        return None if self._own is None else list(self._own)

    @classmethod
    def from_bytes(cls, data, *, source: str = "atlas field", parts=None,
                   only: Collection[int] | None = None) -> "AtlasField":
        """An atlas field from the bytes of its file (:meth:`write_to`, or
        :meth:`write_parts` with its parts).

        Each chart is restored by :meth:`Field.from_bytes` (on the shard
        pool) and checked against the atlas (dimension, channels, warp).

        Parameters
        ----------
        data : bytes-like
        source : str
            Named in error messages.
        parts : callable, optional
            ``parts(key) -> bytes-like``: a part of a file written by
            :meth:`write_parts` (needed for those files only). A part whose
            bytes do not match its key is damaged.
        only : collection of int, optional
            Restore these charts only (the others stay empty: a shard held in
            another process); only their parts are read. ``nsamples`` is then
            theirs (:attr:`own_samples`), or the whole field's when the file did
            not record the charts' own samples (:attr:`own_samples` None).

        Raises
        ------
        SnapshotError
            The data or a part are truncated, damaged or of another format,
            or the file names parts and ``parts`` is not given.
        """
        data = memoryview(data)
        version, meta, off = read_header(data, magic=ATLAS_MAGIC,
                                         versions=(_VERSION, _VERSION_PARTS),
                                         kind="atlas field", source=source)
        try:
            atlas = Atlas.from_dict(meta["atlas"])
            ncharts = int(meta["charts"])
            obj = cls(atlas, int(meta["channels"]), roundtrip_tol=float(meta["roundtrip_tol"]))
            nsamples, nrejected = int(meta["nsamples"]), int(meta["nrejected"])
            own = meta.get("own")
            if own is not None:
                own = [int(x) for x in own]
                if len(own) != ncharts or sum(own) != nsamples:
                    raise ValueError("its charts' own samples do not add up")
        except (KeyError, TypeError, ValueError, InvalidInputError) as exc:
            raise corrupted("atlas field", source, exc) from None
        if ncharts != atlas.ncharts:
            raise SnapshotError(f"{source}: {ncharts} chart files for {atlas.ncharts} charts")
        if only is not None:
            only = frozenset(int(c) for c in only)
            if own is not None:
                nsamples = sum(own[c] for c in only)
        obj._own = own
        # a field saved before its first batch was inserted (its unit perhaps chosen in
        # memory already) may still take the unit of the batch first in the log
        obj._chooses_unit = atlas.unit_from_data or bool(meta.get("chooses_unit"))
        if version == _VERSION_PARTS:
            return obj._restore_parts(meta, nsamples, nrejected, len(data) - off, parts, source,
                                      only)
        blobs = []
        for i in range(ncharts):
            if off + _LENGTH.size > len(data):
                raise SnapshotError(f"{source}: truncated at chart {i}")
            (size,) = _LENGTH.unpack_from(data, off)
            off += _LENGTH.size
            if off + size > len(data):
                raise SnapshotError(f"{source}: truncated at chart {i}")
            if only is None or i in only:
                blobs.append((i, data[off:off + size]))
            off += size
        if off != len(data):
            raise SnapshotError(f"{source}: {len(data) - off} bytes after the last chart")
        restored = obj._over_shards(
            lambda _, ib: (ib[0], Field.from_bytes(ib[1], source=f"{source}: chart {ib[0]}")),
            [(i, (i, blob)) for i, blob in blobs])
        obj._adopt(restored, nsamples, nrejected, source)
        return obj

    def _restore_parts(self, meta: dict, nsamples: int, nrejected: int, extra: int, parts,
                       source: str, only: frozenset | None = None) -> "AtlasField":
        keys = meta.get("parts")
        if not (isinstance(keys, list) and len(keys) == len(self.fields)
                and all(isinstance(k, str) and len(k) == 32 for k in keys)):
            raise SnapshotError(f"{source}: damaged list of parts")
        if extra:
            raise SnapshotError(f"{source}: {extra} bytes after the list of parts")
        if parts is None:
            raise SnapshotError(f"{source}: the charts are parts kept apart; pass parts= "
                                "to read them")

        def load(c: int, key: str) -> Field:
            blob = read_part(parts, key, source, f"chart {c}: part")
            return Field.from_bytes(blob, source=f"{source}: chart {c} (part {key})")

        work = [(c, (c, k)) for c, k in enumerate(keys) if only is None or c in only]
        restored = self._over_shards(lambda _, ck: (ck[0], load(*ck)), work)
        self._adopt(restored, nsamples, nrejected, source)
        for c, k in enumerate(keys):  # the restored charts are those parts
            if only is None or c in only:
                self._parts[c] = (0, k)
        return self

    def _adopt(self, restored, nsamples: int, nrejected: int, source: str) -> None:
        """Take the restored ``(chart, Field)`` pairs (checked against the atlas) and
        the counts."""
        atlas = self.atlas
        for i, f in restored:
            if f.ndim != self.ndim or f.channels != self.channels:
                raise SnapshotError(f"{source}: chart {i} does not match the atlas")
            want = atlas.warps[i]
            if (f.warp is None) != (want is None) or (
                    want is not None and f.warp.to_dict() != want.to_dict()):
                raise SnapshotError(f"{source}: chart {i}'s warp does not match the atlas's")
            self.fields[i] = f
        self._nsamples, self._nrejected = nsamples, nrejected

    def __repr__(self) -> str:
        return (f"AtlasField(k={self.k}, d={self.d}, charts={self.atlas.ncharts}, "
                f"oriented={self.atlas.oriented}, channels={self.channels}, "
                f"nsamples={self.nsamples}, nstored={self.nstored})")


#: Multiples of :func:`flatserve.atlas.data_unit` that :func:`fitted_unit` tries.
FIT_FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: Steps :func:`fitted_unit` takes beyond an end of its grid while the least error
#: is there.
FIT_EXTEND = 3


def _chart_dim(k: int, d: int) -> int:
    """Dimensions of a chart's triangulation of k-flats in R^d (``m - 1``)."""
    return basis_size(k, d) - 1


def fit_max_rows(k: int, d: int) -> int:
    """The rows :func:`fitted_unit` uses at most for k-flats in R^d: 4,000 while a
    chart's triangulation has at most 4 dimensions (``basis_size(k, d) - 1``: up
    to R^3, and hyperplanes in R^4), 2,000 up to 6 (lines and planes in R^4),
    1,000 beyond.

    A fit builds 6-9 fields of 3/4 of its rows, and a sample's cells grow fast
    with the dimension (about 20 cells a vertex in 4 dimensions, 300-430 in 6:
    docs/costs.md). Lines in R^4, 3,000 samples: 4,000 rows took 97 s on a
    loaded machine and chose 3.81, 2,000 rows 26 s and 1.90, whose fields'
    errors were 0.57 and 0.59 times the 8 nearest samples'.

    >>> fit_max_rows(1, 3), fit_max_rows(2, 4), fit_max_rows(3, 5)
    (4000, 2000, 1000)
    """
    dim = _chart_dim(k, d)
    return 4000 if dim <= 4 else 2000 if dim <= 6 else 1000


class FittedUnit(NamedTuple):
    """What :func:`fitted_unit` chose, and why.

    Attributes
    ----------
    unit : float
        The candidate chosen: of those whose score is within the margin of the
        least, the nearest to ``data_unit``.
    candidates : ndarray, shape (u,)
        The units tried (increasing; ``data_unit`` times ``factors``, and the
        steps beyond an end).
    errors : ndarray, shape (u,)
        Their scores (``metric``) on the held-out rows every candidate answered.
    compared : int
        How many held-out rows that was.
    """

    unit: float
    candidates: np.ndarray
    errors: np.ndarray
    compared: int


def fitted_unit(atlas: Atlas, flats: Flats, values, *, factors=FIT_FACTORS,
                holdout: float = 0.25, max_rows: int | None = None, seed: int = 0,
                metric: str = "rmse", margin: float = 0.05) -> FittedUnit:
    """The unit of length (:class:`~flatserve.atlas.Atlas` ``unit``) that interpolates
    these samples best, by held-out validation.

    ``data_unit(flats, values)`` (the geometry of the flats alone) times each of
    ``factors`` is tried (and, while the least error is at an end of them, up to
    :data:`FIT_EXTEND` more steps beyond it): a field over ``atlas.with_unit(u, net=False)``
    (without the net of the outer seam, whose thinning depends on the unit) is filled with a
    seeded ``1 - holdout`` share of the rows (at most ``max_rows`` in all) and
    queried at the rest, and scored on the held-out rows every candidate
    answered (``metric``).  Of the units whose score is within ``margin`` of the
    least, the one nearest the geometry's wins: a grid whose scores differ by
    less than the noise of a small held-out set (the light-field scenes: the
    geometry's within 1-3 % of the least) keeps the geometry's.  The
    unit balances turns against shifts (a shift of ``unit`` weighs as a turn of
    one radian); the best balance depends on how fast the values change along
    each, which the geometry cannot tell.  It costs ``len(factors)`` builds of
    ``(1 - holdout) * min(n, max_rows)`` samples (lines in R^3, 3,000 samples:
    about a second; lines and planes in R^4, 2,000 rows: 15-30 s).

    Parameters
    ----------
    atlas : Atlas
        The charts (their unit is replaced).
    flats : Flats
        ``n`` sample flats; at least 40 rows.
    values : (n, C) or (n,) array_like
        Their values (finite).
    factors : sequence of float
        Multiples of ``data_unit`` to try (positive).
    holdout : float
        Share of the rows held out, in (0, 1).
    max_rows : int, optional
        Rows used at most (a seeded subset of them); default
        :func:`fit_max_rows` of the atlas's kind.
    seed : int
    metric : {"rmse", "median"}
        The score of a unit: the root mean square of its held-out errors (mean
        over channels; what a PSNR measures) or their median absolute value.
    margin : float
        Share in [0, 1): scores within ``(1 + margin)`` times the least count as
        equal (the nearest to the geometry's unit wins among them).

    Returns
    -------
    FittedUnit

    Example
    -------
    >>> import numpy as np, flatserve
    >>> from flatserve.atlas import Atlas
    >>> rng = np.random.default_rng(0)
    >>> o, v = rng.uniform(-1, 1, (1500, 3)), rng.normal(size=(1500, 3))
    >>> f = flatserve.Flats.from_rays(o, v)
    >>> a = v / np.linalg.norm(v, axis=1, keepdims=True)   # (a line's value: even in a)
    >>> fit = fitted_unit(Atlas.covering(1, 3), f, np.cos(3 * a[:, 0]) * np.cos(2 * a[:, 1]))
    >>> bool(fit.unit > 2 * fit.candidates[0])   # values that change with the turn: a long unit
    True
    """
    n = atlas.check_flats(flats).n
    vals = np.asarray(values, dtype=np.float64)
    if vals.ndim not in (1, 2) or vals.shape[0] != n:
        raise InvalidInputError(f"values: expected shape ({n},) or ({n}, C), got "
                                f"{vals.shape}", "values")
    vals = vals.reshape(n, -1)
    if not np.isfinite(vals).all():
        raise InvalidInputError("values: a unit is fitted to finite values only", "values")
    if not 0.0 < float(holdout) < 1.0:
        raise InvalidInputError(f"holdout: expected a share in (0, 1), got {holdout!r}",
                                "holdout")
    if not (isinstance(margin, (int, float)) and 0 <= margin < 1):
        raise InvalidInputError(f"margin: expected a share in [0, 1), got {margin!r}", "margin")
    if metric not in ("rmse", "median"):
        raise InvalidInputError(f"metric: expected 'rmse' or 'median', got {metric!r}", "metric")
    fac = np.asarray(factors, dtype=np.float64).reshape(-1)
    if fac.size == 0 or not (np.isfinite(fac) & (fac > 0)).all():
        raise InvalidInputError(f"factors: expected positive multiples, got {factors!r}",
                                "factors")
    rng = np.random.default_rng(seed)
    if max_rows is None:
        max_rows = fit_max_rows(atlas.k, atlas.d)
    rows = rng.permutation(n)[:max(int(max_rows), 0)]
    test = np.sort(rows[:int(round(holdout * rows.size))])
    train = np.sort(rows[test.size:])
    if train.size < 30 or test.size < 10:
        raise InvalidInputError(f"flats: fitting a unit needs at least 30 rows to build and "
                                f"10 to hold out, got {train.size} and {test.size} of {n}",
                                "flats")
    base = data_unit(flats, vals)  # every row's geometry: kept when the fit cannot tell
    exact = 1e-12 * max(float(np.abs(vals).max()), 1e-300)  # errors at round-off: ties
    tried: dict[float, np.ndarray] = {}

    def errors_of(u: float) -> None:
        fld = AtlasField(atlas.with_unit(u, net=False), channels=vals.shape[1])
        fld.add(flats.take(train), vals[train])
        got = np.asarray(fld.query(flats.take(test)).values)
        tried[u] = (np.square(got - vals[test]) if metric == "rmse"
                    else np.abs(got - vals[test])).mean(axis=1)

    def score(errs: np.ndarray) -> np.ndarray:
        return np.sqrt(errs.mean(axis=1)) if metric == "rmse" else np.median(errs, axis=1)

    def least(units: np.ndarray, sc: np.ndarray) -> int:
        # of the units within `margin` of the least error, the one nearest the
        # geometry's (ties: e.g. every candidate exact on the held-out rows)
        near = np.flatnonzero(sc <= sc.min() * (1 + margin) + exact)
        return int(near[np.abs(np.log(units[near] / base)).argmin()])

    for u in np.unique(np.clip(base * fac, MIN_UNIT, MAX_UNIT)):
        errors_of(float(u))
    for _ in range(FIT_EXTEND):  # the least at an end of the grid: one more step beyond
        units = np.array(sorted(tried))
        errs = np.stack([tried[u] for u in units])  # (u, test)
        both = np.isfinite(errs).all(axis=0)
        if not both.any():
            raise InvalidInputError("flats: no held-out row was answered by every candidate "
                                    "unit (too few samples, or too spread out)", "flats")
        best = int(score(errs[:, both]).argmin())  # (the margin: for the choice only)
        if units.size < 2 or 0 < best < units.size - 1:
            break
        step = units[-1] / units[-2] if best else units[0] / units[1]
        nxt = float(np.clip(units[best] * step, MIN_UNIT, MAX_UNIT))
        if nxt in tried:
            break
        errors_of(nxt)
    units = np.array(sorted(tried))
    errs = np.stack([tried[u] for u in units])
    both = np.isfinite(errs).all(axis=0)
    sc = score(errs[:, both])
    return FittedUnit(float(units[least(units, sc)]), units, sc, int(both.sum()))


#: The fewest rows a first batch needs for ``unit="fit"`` (:func:`choose_unit`):
#: :func:`fitted_unit` builds on 3/4 of them and holds out the rest.
FIT_MIN_ROWS = 200


def choose_unit(atlas: Atlas, flats: Flats, values) -> float:
    """The unit of length a field over ``atlas`` takes from its first batch, by the
    atlas's :attr:`~flatserve.atlas.Atlas.unit_rule`.

    ``"data"``: :func:`flatserve.atlas.data_unit` (the geometry of the flats).
    ``"fit"``: :func:`fitted_unit` (held-out validation on the values; its
    defaults: at most :func:`fit_max_rows` rows, seeded), or ``data_unit`` when the batch has
    fewer than :data:`FIT_MIN_ROWS` rows or no held-out row was answered by every
    candidate.  Deterministic: the same batch gives the same unit (a writer
    stores it with the batch; a replica or a restart takes it from there).

    Parameters
    ----------
    atlas : Atlas
        With ``unit_from_data`` (a unit still to choose).
    flats : Flats
        ``n`` flats of the atlas's kind.
    values : (n, C) array_like
        Their values (finite).

    Returns
    -------
    float

    Example
    -------
    >>> import numpy as np, flatserve
    >>> from flatserve.atlas import Atlas, data_unit
    >>> rng = np.random.default_rng(0)
    >>> f = flatserve.Flats.from_rays(rng.uniform(-1, 1, (100, 3)), rng.normal(size=(100, 3)))
    >>> v = rng.normal(size=(100, 1))
    >>> choose_unit(Atlas.covering(1, 3, unit=None), f, v) == data_unit(f, v)
    True
    """
    if atlas.unit_rule != "fit" or flats.n < FIT_MIN_ROWS:
        return data_unit(flats, values)
    try:
        return fitted_unit(atlas, flats, values).unit
    except InvalidInputError as exc:
        if exc.argument != "flats":  # (bad values are the caller's: raised)
            raise
        return data_unit(flats, values)
