"""The query room: interpolation of a field at a batch of flats.

:class:`QueryService` answers a query in the domain's terms (a
:class:`~flatserve.field.QueryResult`); the endpoint that decodes a body, asks it
and encodes the answer is :func:`flatserve.service.http.query.answer`. Queries of
fewer than :data:`SMALL_QUERY_ROWS` rows run on one native thread (the request is
the unit of parallelism). A small query of a field whose shards live in other
processes (cluster mode: the field's ``holds_shards``) is routed and blended on the
event loop and its shards' answers awaited there (:meth:`QueryService.query_inline`):
no thread hop.
"""
from __future__ import annotations

from dataclasses import dataclass

import anyio.to_thread

from ...field import QueryResult
from ...flats import Flats
from ...options import Interpolant
from .catalogue import FieldCatalogue
from .entry import FieldEntry
from .replica import Follower
from ..settings import Settings
from ..status import FieldNotFoundError, InvalidParameterError, NotReadyError

#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048


@dataclass
class QueryService:
    """Interpolation of this replica's fields."""

    #: ``read_wait_timeout``, ``apply_wait_timeout``
    settings: Settings
    #: finds the field a query names
    catalogue: FieldCatalogue
    #: for reads that wait for a log position
    follower: Follower
    #: counts the queries and their rows per field (a ``Metrics``; None: not counted)
    metrics: object = None

    def query(self, e: FieldEntry, flats: Flats, *, weights: bool = False, wait: bool = False,
              **kw) -> QueryResult | None:
        """Interpolate field ``e`` at ``flats`` (keywords of the field's ``query``;
        ``blocking=False`` gives None instead of waiting for an insert; ``wait``
        first waits until every acknowledged batch is indexed here).

        Raises
        ------
        InvalidInputError
            ``weights`` for a field whose answers blend several shards (422).
        NotReadyError
            ``wait`` and the batches are not indexed in ``apply_wait_timeout`` (503).
        """
        self._check(e, flats, weights, kw)
        timeout = self.settings.apply_wait_timeout
        if wait and not self.follower.wait_all_committed(timeout):
            raise NotReadyError(f"field {e.name!r}: the acknowledged batches are not indexed "
                                f"here yet (waited at most {timeout:g} s, "
                                "FLATSERVE_APPLY_WAIT_TIMEOUT, or the server is stopping); "
                                "retry shortly")
        return self._counted(e, e.field.query(flats, return_weights=weights, **kw))

    async def query_inline(self, e: FieldEntry, flats: Flats, *, weights: bool = False,
                           **kw) -> QueryResult | None:
        """A small query answered on the event loop (never waiting on it): at once by a
        field held here, None if an insert holds it (:meth:`query` with
        ``blocking=False``) or it asks for the gradient interpolant (whose slopes
        may need a k-d tree built); a field whose shards live in other processes
        (its ``query_async``) routes and blends here and awaits their answers.

        Raises
        ------
        InvalidInputError, ShardUnavailableError
            As :meth:`query`, and the field's ``query_async``.
        """
        if e.field.holds_shards:  # (the one place a query asks where the shards are)
            if kw.get("interpolant", Interpolant.LINEAR) is not Interpolant.LINEAR:
                return None  # its first query after an insert builds a k-d tree: not here
            return self.query(e, flats, weights=weights, blocking=False, **kw)
        self._check(e, flats, weights, kw)
        return self._counted(e, await e.field.query_async(flats, return_weights=weights, **kw))

    def _check(self, e: FieldEntry, flats: Flats, weights: bool, kw: dict) -> None:
        """A query's checks before it runs (and one native thread for small ones)."""
        if len(flats) < SMALL_QUERY_ROWS:  # not worth starting native worker threads
            kw.setdefault("threads", 1)
        if e.deleted:
            raise FieldNotFoundError(f"no field named {e.name!r}")
        if weights and e.field.blends:
            n = len(e.field.shards)
            raise InvalidParameterError(
                f"weights: field {e.name!r} is an atlas field ({n} chart{'s' * (n != 1)}): "
                "its answers are blends over its charts, whose sample ids and weights the "
                "service does not return; a field created with basis {\"kind\": "
                "\"tangent_simplex\"} (no atlas) returns them", "weights")

    def _counted(self, e: FieldEntry, res: QueryResult | None) -> QueryResult | None:
        if res is not None and self.metrics is not None:
            self.metrics.queries.labels(e.name).inc()
            self.metrics.query_rows.labels(e.name).inc(len(res.inside))
        return res

    async def wait_position(self, position: int | None) -> None:
        """Return once this replica has applied log ``position`` (at once when it has:
        no thread hop); :class:`~flatserve.service.status.ReplicaBehindError` (503,
        ``Retry-After``) after ``read_wait_timeout`` seconds."""
        if position is None or self.follower.applied >= position:
            return
        await anyio.to_thread.run_sync(self.follower.wait_position, position,
                                       self.settings.read_wait_timeout)


