"""The query room: interpolation of a field at a batch of flats, and the one
implementation of ``POST /v1/fields/{name}/query``.

:class:`QueryService` answers a query in the domain's terms (a
:class:`~flatserve.field.QueryResult`); :func:`answer` is the endpoint: it
decodes the body, asks the service and encodes the response. The FastAPI route
(:func:`flatserve.service.http.routes.query_field`, the documented reference) and
the lean ASGI path (:mod:`.fastpath`, which skips FastAPI's per-request
machinery on the hot endpoint) both call it with a :class:`QueryParams`
validated by the same model.

Where the work runs: small bodies are decoded on the event loop, larger ones
in the thread pool; queries of fewer than :data:`INLINE_ROWS` rows run (and are
encoded) inline on one native thread unless an insert may hold the field (they
would wait on the loop) or they ask for the gradient interpolant (whose first
query after an insert builds a chart's neighbour tree), everything else in the thread pool (the C++ releases
the GIL), its answer encoded there too. A small query of a field whose shards
live in other processes (cluster mode: the field has ``query_async``) is
routed and blended on the event loop and its shards' answers awaited there
(:meth:`QueryService.query_inline`): no thread hop. An answer larger than
``max_json_answer_bytes`` (JSON) or ``max_answer_bytes`` is refused (413) before
the query runs (:func:`.codec.check_answer`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import anyio.to_thread
from fastapi import Response
from pydantic import BaseModel, Field

from ...errors import InvalidInputError
from ...field import QueryResult
from ...flats import Flats
from ...options import Form, Interpolant, Order, Outside
from ..http import codec
from .catalogue import FieldCatalogue
from .entry import FieldEntry
from .replica import Follower
from ..schemas import MIN_POSITION_DESCRIPTION
from ..settings import Settings
from ..status import FieldNotFoundError, InvalidParameterError, NotReadyError

#: queries with fewer rows run inline on the event loop (about 0.1-0.3 ms of CPU)
INLINE_ROWS = 64
#: bodies larger than this are decoded and validated in the thread pool
INLINE_BODY_BYTES = 64 * 1024
#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048


class QueryParams(BaseModel):
    """The query parameters of ``POST /v1/fields/{name}/query`` (the route's query
    model, and what the lean path validates the query string with)."""

    form: Optional[Form] = Field(
        None, description="Flat form of the body. JSON/.npz: inferred from the array names. "
                          "`.npy`: required unless the field holds lines (k = 1; default "
                          "`rays`) or points (k = 0; default `points`).")
    outside: Outside = Outside.NAN
    order: Order = Order.HILBERT
    interpolant: Interpolant = Field(
        Interpolant.LINEAR,
        description="`linear` (the paper's): the Delaunay cell's values, barycentrically "
                    "weighted. `gradient`: the cell's vertices' first-order Taylor "
                    "expansions, barycentrically weighted, each slope fitted to the vertex's "
                    "3D+2 nearest samples (D: the chart's dimension) and each expansion "
                    "limited to the values near its vertex. Lower error on smooth functions "
                    "(a quarter to a half in 4-6 dimensions at 3,000 samples: docs/costs.md); "
                    "on light fields with sharp edges about the linear answer. The same "
                    "cells: queries outside the hull keep the linear answer, and `weights` "
                    "are the cell's either way.")
    weights: bool = Field(False, description="Also return sample ids and weights.")
    status: bool = Field(False, description="`.npy` answers: also a last column of status codes "
                                            "(rows `values | inside | status`; JSON and `.npz` "
                                            "answers always carry `status`).")
    wait: bool = Field(False, description="First wait until every batch acknowledged so far, "
                                          "by any replica (also with wait=false), is indexed "
                                          "here.")
    min_position: Optional[int] = Field(None, ge=0, description=MIN_POSITION_DESCRIPTION)


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


def server_timing(t: dict) -> str:
    """``Server-Timing`` header (milliseconds) of the phases of a request."""
    return ", ".join(f"{k};dur={v * 1e3:.3f}" for k, v in t.items())


async def answer(queries: QueryService, name: str, params: QueryParams, body: bytes,
                 content_type: str | None, accept: str | None) -> Response:
    """Interpolate field ``name`` at the flats of ``body``; the HTTP response."""
    t0 = time.perf_counter()
    await queries.wait_position(params.min_position)
    e = queries.catalogue.get(name)
    settings = queries.settings

    def decode():
        return codec.decode(body, content_type, params.form, k=e.spec.k, d=e.spec.d,
                            field=e.name, channels=None, max_rows=settings.max_batch_rows,
                            max_json_bytes=settings.max_json_bytes)[0]

    if len(body) <= INLINE_BODY_BYTES:
        flats = decode()
    else:
        flats = await anyio.to_thread.run_sync(decode)
    kind = codec.accept_kind(accept)
    w = params.weights
    st = params.status
    codec.check_answer(len(flats), codec.query_numbers(kind, e.spec.channels, e.field.ndim, w, st),
                       kind, max_json=settings.max_json_answer_bytes,
                       max_binary=settings.max_answer_bytes,
                       bulk=f"ask for {codec.NPY} (Accept header), the bulk answer"
                       if kind == "json" else "")
    kw = {"outside": params.outside, "order": params.order, "weights": w,
          "interpolant": params.interpolant}
    t1 = time.perf_counter()
    times: dict = {}

    def encode(res: QueryResult) -> Response:
        t = time.perf_counter()
        times["query"] = t - t1
        out = codec.query_response(accept, res.values, res.inside, res.status,
                                   res.ids if w else None, res.weights if w else None,
                                   npy_status=st)
        times["encode"] = time.perf_counter() - t
        return out

    resp = None
    if len(flats) < INLINE_ROWS and not params.wait:  # inline, unless an insert holds the field
        res = await queries.query_inline(e, flats, threads=1, **kw)
        if res is not None:
            resp = encode(res)
    if resp is None:  # the query and its encoding off the event loop
        resp = await anyio.to_thread.run_sync(
            lambda: encode(queries.query(e, flats, wait=params.wait, **kw)))
    resp.headers["Server-Timing"] = server_timing({"decode": t1 - t0, **times})
    return resp
