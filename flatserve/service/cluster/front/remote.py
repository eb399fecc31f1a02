"""The front's view of a field whose shards live elsewhere: :class:`RemoteField`.

It implements the field contract (:class:`flatserve.contract.SampledField`) with no
triangulation: routing, charting decisions and blending use an empty field of the
definition; each group's half of a query or a snapshot runs where the group lives
(:class:`ShardGroups`). Writes go nowhere: the shard workers follow the log. A query
waits until every shard it touches has applied the front's log position for the
field (read-your-writes through any front). docs/design.md, "Fronts".
"""
from __future__ import annotations

import os
from typing import Any, Callable, Collection, Protocol, Sequence

import numpy as np

from ....contract import part_pointer
from ....field import AddResult, QueryResult, QueryRoute
from ....flats import Flats
from ....options import Interpolant, Order, Outside, choice
from ...rooms.units import adopt_unit
from .. import wire
from ..wire import ShardCall
from ...status import NotReadyError, ShardUnavailableError

_NO_ROWS = np.empty(0, np.int64)


class ShardGroups(Protocol):
    """Where a field's shard groups live, and how a front calls them.

    Attributes
    ----------
    charts : list of tuple of int
        Per group, its charts (every chart in exactly one group).
    """

    charts: list[tuple[int, ...]]

    def call(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """``{group: call}`` (:mod:`..wire`) on one live copy of each group, at once:
        ``{group: result}`` (ShardUnavailableError: a group has no live copy)."""
        ...

    async def call_async(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """:meth:`call` awaited on the event loop (nothing in it blocks the loop)."""
        ...

    def status(self) -> list[dict | None]:
        """Per group, the last status a copy reported (never waits; None: none yet)."""
        ...

    def placement(self) -> list[dict]:
        """Per group what :meth:`RemoteField.describe` reports as ``placement``."""
        ...

    def refresh(self) -> None:
        """Ask every copy for its status now (a round of a few seconds at most)."""
        ...

    def applied(self, position: int, timeout: float) -> list[dict]:
        """Per group, a copy's status once it has applied the log up to ``position``
        (ShardUnavailableError: none there within ``timeout``)."""
        ...


class _Lazy:
    """A batch's decisions, charted on first use (an upload's response needs them;
    the follower's hand-over of another front's batch never does). ``unit``: the
    unit of length it is charted in, when it is to become the field's."""

    def __init__(self, chart: Callable[[], Any], nrows: int, unit: float | None = None) -> None:
        self._chart, self.nrows, self.unit, self._done = chart, nrows, unit, None

    @property
    def decided(self) -> bool:
        return self._done is not None

    def _get(self):  # (no lock: two threads may chart it twice, the same decisions)
        if self._done is None:
            self._done = self._chart()
        return self._done

    accepted = property(lambda self: self._get().accepted)
    rejected = property(lambda self: self._get().rejected)
    reasons = property(lambda self: self._get().reasons)


def _lazy_prepare(shape, flats: Flats, values, defer: bool, only, unit: float | None):
    chart = shape.prepare(flats, values, defer=True, only=only)
    lazy = _Lazy(chart, len(flats), unit)
    return (lambda: lazy) if defer else lazy


class _InUnit:
    """A remote field's definition in another unit of length: it charts a batch's
    decisions only (:meth:`RemoteField.in_unit`)."""

    def __init__(self, shape, unit: float) -> None:
        self._shape, self.unit = shape, unit

    def prepare(self, flats: Flats, values, *, defer: bool = False, only=None):
        return _lazy_prepare(self._shape, flats, values, defer, only, self.unit)


class RemoteField:
    """A field whose shards live in other processes (see the module doc).

    Parameters
    ----------
    shape : Field or AtlasField
        An empty field of the definition (``FieldSpec.new_field``): routing,
        charting decisions, blending, the snapshot's header.
    groups : ShardGroups
    position : callable
        The field's log position the front has seen (its entry's
        ``indexed_position``): what an answer must reflect.
    timeout : float
        Seconds a query waits for a shard (behind, or restoring) before 503.
    """

    def __init__(self, shape, groups: ShardGroups, position: Callable[[], int],
                 timeout: float) -> None:
        self._shape = shape
        self.groups = groups
        self._position = position
        self.timeout = float(timeout)
        self.k, self.d, self.ndim = shape.k, shape.d, shape.ndim
        self.channels, self.roundtrip_tol, self.blends = \
            shape.channels, shape.roundtrip_tol, shape.blends
        n = len(shape.shards)
        self._group_of = np.full(n, -1, dtype=np.int64)
        for g, charts in enumerate(groups.charts):
            self._group_of[list(charts)] = g
        if (self._group_of < 0).any():
            raise ValueError("groups: every chart must be in a group")
        #: bytes of parts the groups stored for the last :meth:`write_parts`
        self.stored_bytes = 0

    #: the shards live in other processes: answers are awaited (:meth:`query_async`)
    holds_shards = False

    # -- sizes (the workers' last reports: never waits; describe asks them first) ---------
    def _statuses(self) -> list[dict]:
        return [s for s in self.groups.status() if s is not None]

    def _sum(self, key: str) -> int:
        return int(sum(s[key] for s in self._statuses()))

    nsamples = property(lambda self: self._sum("nsamples"))
    nstored = property(lambda self: self._sum("nstored"))
    nsimplex = property(lambda self: self._sum("nsimplex"))

    @property
    def nrejected(self) -> int:
        st = self.groups.status()
        return int(st[0]["nrejected"]) if st and st[0] is not None else 0

    @property
    def shards(self):
        """The definition's shards (empty here: their sizes are :meth:`describe`'s)."""
        return self._shape.shards

    @property
    def own_samples(self) -> list[int] | None:
        """Per chart, its own samples as its shard last reported them (None until
        every chart's shard has reported them; a one-chart field: ``[nsamples]``)."""
        if not self.blends:
            return [self.nsamples]
        own = self._chart_own()
        return None if any(n is None for n in own) else [int(n) for n in own if n is not None]

    @property
    def ntiles(self) -> int | None:
        """None: the tiles of a chart held elsewhere are not counted here."""
        return None

    def _chart_own(self) -> list[int | None]:
        own: list[int | None] = [None] * len(self._shape.shards)
        for s in self._statuses():
            for c, n in zip(s["charts"], s.get("chart_own", ())):
                own[c] = n
        return own

    # -- routing and blending: the definition's -------------------------------------------
    def route(self, flats: Flats) -> list[np.ndarray]:
        return self._shape.route(flats)

    def route_query(self, flats: Flats) -> QueryRoute:
        return self._shape.route_query(flats)

    def blend(self, route: QueryRoute, results: Sequence[QueryResult | None], *,
              return_weights: bool = False) -> QueryResult:
        return self._shape.blend(route, results, return_weights=return_weights)

    def copies(self, flats: Flats) -> float:
        """The definition's copies of ``flats``, with a dense seam's charts judged by
        their own samples as their shards last reported them (a chart whose shard
        has not reported counts as sparse: more copies, the safe side)."""
        if not self.blends:  # one chart: nothing to judge
            return self._shape.copies(flats)
        return self._shape.copies(flats, own=self._chart_own())

    # -- the unit of length of a field whose first batch chooses it: the upload room
    # chooses it here and stores it with the batch; the workers take it from there
    @property
    def atlas(self):
        """The definition's atlas (atlas fields), in the unit the field took."""
        return self._shape.atlas

    @property
    def unit_pending(self) -> bool:
        """The field's unit is still to be taken from its first batch."""
        return bool(self._shape.unit_pending)

    @property
    def unit_from_data(self) -> bool:
        """A batch charted now may set the field's unit (:attr:`unit_pending`: the
        front's definition holds no samples; the first batch in the log fixes it)."""
        return self.unit_pending

    @property
    def unit(self) -> float | None:
        """The definition's unit of length (None while pending, or for one chart)."""
        return self._shape.unit

    def settle_unit(self, unit: float, *, if_empty: bool = False) -> bool:
        """Take ``unit`` (recorded with the field's first batch) while the field has
        none; a field that has one keeps it and returns False."""
        if not self.unit_pending:
            return False
        return self._shape.settle_unit(unit, if_empty=if_empty)

    def in_unit(self, unit: float):
        """This field, or one that charts a batch's decisions in ``unit`` (its prepared
        batches carry the unit)."""
        shape = self._shape.in_unit(unit)
        return self if shape is self._shape else _InUnit(shape, float(unit))

    # -- writes: the workers follow the log ------------------------------------------------
    def prepare(self, flats: Flats, values, *, defer: bool = False, only=None):
        """Validate now; chart (for the decisions) when they are first read."""
        return _lazy_prepare(self._shape, flats, values, defer, only, None)

    def insert_prepared(self, batch, *, slice_rows: int | None = None) -> AddResult:
        """The batch's decisions (the shard workers insert it from the log)."""
        if batch.decided:
            return AddResult(accepted=batch.accepted, rejected=batch.rejected,
                             reasons=batch.reasons, duplicates=0, nsamples=self.nsamples)
        return AddResult(accepted=batch.nrows, rejected=_NO_ROWS, reasons=[], duplicates=0,
                         nsamples=self.nsamples)

    def applied_counts(self, position: int, timeout: float) -> dict:
        """Once every group has applied the batch at log ``position`` (asked now): the
        field's ``nsamples`` then and the batch's ``duplicates`` (the groups' sum; None
        when a copy that answered restored itself past the batch), for an upload with
        ``wait=true``.

        Raises
        ------
        ShardUnavailableError
            A group has no copy at ``position`` within ``timeout`` (503: the batch
            is stored; a retry with its Idempotency-Key answers once it is applied).
        """
        try:
            got = self.groups.applied(position, timeout)
        except ShardUnavailableError as exc:
            raise ShardUnavailableError(
                f"the batch at log position {position} is stored, but not every shard of the "
                f"field has applied it ({exc}): retry with the same Idempotency-Key for its "
                "response, or upload with wait=false") from None
        dups = [s.get("duplicates") for s in got]
        return {"nsamples": int(sum(s["nsamples"] for s in got)),
                "duplicates": None if None in dups else int(sum(dups))}

    def add(self, flats: Flats, values) -> AddResult:
        return self.insert_prepared(self.prepare(flats, values))

    def settle(self) -> None:
        """Nothing here: each shard worker settles its charts as it applies a batch."""

    # -- reads ------------------------------------------------------------------------------
    def query(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
              order: Order | str = Order.HILBERT, threads: int | None = None,
              return_weights: bool = False, blocking: bool = True,
              interpolant: Interpolant | str = Interpolant.LINEAR) -> QueryResult | None:
        """Route, one call per shard group touched (each its charts' answers), blend.

        Not ``blocking``: None at once (an answer from other processes always
        waits for them; the caller runs it off its event loop, or awaits
        :meth:`query_async`).

        Raises
        ------
        ShardUnavailableError
            A shard the query needs has no live copy, or has not applied the
            field's log position within ``timeout`` (503): never a partial answer.
        """
        if not blocking:
            return None
        route, calls = self._fan_out(flats, outside, order, threads, return_weights, interpolant)
        return self._blend(route, calls, self.groups.call(calls, self.timeout + 5.0),
                           return_weights)

    async def query_async(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
                          order: Order | str = Order.HILBERT, threads: int | None = None,
                          return_weights: bool = False,
                          interpolant: Interpolant | str = Interpolant.LINEAR) -> QueryResult:
        """:meth:`query` with the shards' answers awaited on the event loop (small
        queries: routing, submission and blending take a fraction of a millisecond)."""
        route, calls = self._fan_out(flats, outside, order, threads, return_weights, interpolant)
        got = await self.groups.call_async(calls, self.timeout + 5.0)
        return self._blend(route, calls, got, return_weights)

    def _fan_out(self, flats: Flats, outside, order, threads, return_weights, interpolant):
        """The query's route and its calls: per group touched, :func:`..wire.query` of
        ``work``, the ``(chart, flats)`` of its charts (the workers compute the
        gradient interpolant's slopes, beside their samples)."""
        interpolant = choice(interpolant, Interpolant, "interpolant")
        route = self._shape.route_query(flats)
        kw = {"outside": outside, "order": order, "threads": threads,
              "return_weights": return_weights}
        if interpolant is not Interpolant.LINEAR:  # (a worker of an older release: linear)
            kw["interpolant"] = interpolant.value
        whole = len(route.rows) == 1
        per: dict[int, list] = {}
        for c, rows in enumerate(route.rows):
            if rows.size:
                per.setdefault(int(self._group_of[c]), []).append(
                    (c, flats if whole else flats.take(rows)))
        at = self._position()
        return route, {g: wire.query(w, kw, at, self.timeout) for g, w in per.items()}

    def _blend(self, route: QueryRoute, calls: dict, got: dict, return_weights: bool):
        """The field's answer from each group's answers, in chart order."""
        results: list = [None] * len(route.rows)
        for g, call in calls.items():
            for (c, _), res in zip(call.work, got[g]):
                results[c] = res
        return self._shape.blend(route, results, return_weights=return_weights)

    def describe(self) -> dict:
        """The contract's keys counted from the workers' reports, asked now
        (:meth:`ShardGroups.refresh`), and per group its ``placement``
        (:meth:`ShardGroups.placement`)."""
        self.groups.refresh()
        out = self._shape.describe()
        n, stored = self.nsamples, self.nstored
        per_chart = {c: k for s in self._statuses()
                     for c, k in zip(s["charts"], s.get("chart_samples", []))}
        shards = [{"samples": per_chart.get(c)} for c in range(len(self._shape.shards))]
        for chart, sh in zip(out.get("charts") or (), shards):
            chart["samples"] = sh["samples"]
        out.update(nsamples=n, nstored=stored, nsimplex=self.nsimplex, nrejected=self.nrejected,
                   duplication=stored / n if n else None, shards=shards,
                   placement=self.groups.placement())
        return out

    # -- snapshots: every group's parts at one log position, stored by the groups ---------
    def write_parts(self, fh, stage: str | os.PathLike, known: Collection[str] = ()) -> list[str]:
        """The field's snapshot at the front's log position for it: every group held
        there stores its changed parts itself (:meth:`..worker.shard.ShardWorker.parts`:
        ``stage`` stays empty); the field file naming them is written to ``fh`` (a
        one-chart field's: :func:`flatserve.contract.part_pointer` of its one part);
        the bytes the groups stored are :attr:`stored_bytes` afterwards.

        Raises
        ------
        NotReadyError
            A group had already applied a later batch (another try will do), or
            has no live copy (:class:`~flatserve.service.status.ShardUnavailableError`).
        """
        pos = self._position()
        known = list(known)
        self.stored_bytes = 0
        got = self.groups.call({g: wire.parts(pos, known, self.timeout)
                                for g in range(len(self.groups.charts))}, self.timeout + 60.0)
        self.stored_bytes = sum(r["stored"] for r in got.values())
        seqs = {r["seq"] for r in got.values()}
        if len(seqs) != 1:
            raise NotReadyError(f"the shards of the field are at batches {sorted(seqs)}, not "
                                "one; retry the snapshot")
        if got[0]["whole"] is not None:  # one chart: the field file is that part
            fh.write(part_pointer(got[0]["whole"]))  # (in tiles: it names theirs)
            return [got[0]["whole"], *got[0].get("tiles", ())]
        n = len(self._shape.shards)
        keys: list = [None] * n
        own: list = [None] * n
        for r in got.values():
            for (c, key), o in zip(r["parts"], r["own"] or [None] * len(r["parts"])):
                keys[c], own[c] = key, o
        if any(o is None for o in own):
            raise NotReadyError("a shard does not know its charts' own samples yet; retry")
        # the header states the atlas the parts were charted in: with the unit the
        # shards took from the field's first batch (a field whose unit is chosen
        # from its data), which this empty field has not seen
        units = {r["unit"] for r in got.values()} - {None}
        if len(units) > 1:
            raise NotReadyError(f"the shards of the field hold units {sorted(units)}; retry")
        if units:
            adopt_unit(self._shape, units.pop())
        # (after a batch the unit is fixed: the header must not leave it open, as this
        # empty field, which inserts nothing, would)
        fh.write(self._shape.parts_header(keys, own=own, nrejected=got[0]["nrejected"],
                                          unit_fixed=next(iter(seqs)) > 0))
        return keys

    def save_parts(self, path: str | os.PathLike, stage: str | os.PathLike,
                   known: Collection[str] = ()) -> list[str]:
        with open(path, "wb") as fh:
            keys = self.write_parts(fh, stage, known)
            fh.flush()
            os.fsync(fh.fileno())
        return keys

    def to_bytes(self) -> bytes:
        raise NotReadyError("a field whose shards live in a cluster is written as a snapshot "
                            "in parts (write_parts), never whole")

    def write_to(self, fh) -> int:
        return len(self.to_bytes())

    def save(self, path) -> None:
        self.to_bytes()

    def __repr__(self) -> str:
        return (f"RemoteField(k={self.k}, d={self.d}, groups={len(self.groups.charts)}, "
                f"nsamples={self.nsamples})")
