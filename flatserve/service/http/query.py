"""The one implementation of ``POST /v1/fields/{name}/query``: :func:`answer`
decodes the body (:func:`.codec.decode`), asks the query room
(:class:`~flatserve.service.rooms.query.QueryService`) and encodes the response. The
FastAPI route (:func:`.routes.query_field`, the documented reference) and the lean
ASGI path (:mod:`.fastpath`, which skips FastAPI's per-request machinery on the hot
endpoint) both call it with a :class:`QueryParams` validated by the same model.

Where the work runs: small bodies are decoded on the event loop, larger ones in the
thread pool; queries of fewer than :data:`INLINE_ROWS` rows run (and are encoded)
inline unless an insert may hold the field (they would wait on the loop) or they ask
for the gradient interpolant (whose first query after an insert builds a chart's
neighbour tree), everything else in the thread pool (the C++ releases the GIL), its
answer encoded there too. An answer larger than ``max_json_answer_bytes`` (JSON) or
``max_answer_bytes`` is refused (413) before the query runs
(:func:`.codec.check_answer`).
"""
from __future__ import annotations

import time
from typing import Optional

import anyio.to_thread
from fastapi import Response
from pydantic import BaseModel, Field

from ...field import QueryResult
from ...options import Form, Interpolant, Order, Outside
from ..rooms.query import QueryService
from ..schemas import MIN_POSITION_DESCRIPTION
from . import codec


#: queries with fewer rows run inline on the event loop (about 0.1-0.3 ms of CPU)
INLINE_ROWS = 64


#: bodies larger than this are decoded and validated in the thread pool
INLINE_BODY_BYTES = 64 * 1024


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
