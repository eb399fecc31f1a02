"""The query endpoint's one implementation: ``POST /v1/fields/{name}/query``.

:func:`answer` decodes the body, interpolates and encodes the response. The
FastAPI route (:func:`flatserve.service.routes.query_field`, the documented
reference) and the lean ASGI path (:mod:`.fastpath`, which skips FastAPI's
per-request machinery on the hot endpoint) both call it.

Where the work runs: small bodies are decoded on the event loop, larger ones
in the thread pool; queries of fewer than :data:`INLINE_ROWS` rows run inline
on one native thread unless an insert may hold the field (they would wait on
the loop), everything else in the thread pool (the C++ releases the GIL).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal, Optional

import anyio.to_thread
from fastapi import Response

from .status import NotReadyError
from . import codec
from .registry import Registry
from .settings import Settings

#: queries with fewer rows run inline on the event loop (about 0.1-0.3 ms of CPU)
INLINE_ROWS = 64
#: bodies larger than this are decoded and validated in the thread pool
INLINE_BODY_BYTES = 64 * 1024

Form = Literal["rays", "parametric", "flats"]
OUTSIDE = ("nan", "clamp")
ORDERS = ("hilbert", "given")


@dataclass(frozen=True)
class QueryParams:
    """The query parameters of the endpoint (validated by FastAPI or :mod:`.fastpath`)."""

    form: Optional[str] = None
    outside: str = "nan"
    order: str = "hilbert"
    weights: bool = False
    wait: bool = False
    #: read-your-writes: answer once this replica applied this log position
    min_position: Optional[int] = None


def server_timing(t: dict) -> str:
    """``Server-Timing`` header (milliseconds) of the phases of a request."""
    return ", ".join(f"{k};dur={v * 1e3:.3f}" for k, v in t.items())


async def wait_position(registry: Registry, settings: Settings, position: int) -> None:
    """Return once this replica has applied log ``position`` (at once when it has:
    no thread hop); :class:`~flatserve.service.status.ReplicaBehindError` (503,
    ``Retry-After``) after ``read_wait_timeout`` seconds."""
    if registry.position >= position:
        return
    await anyio.to_thread.run_sync(registry.wait_position, position,
                                   settings.read_wait_timeout)


async def answer(registry: Registry, settings: Settings, name: str, params: QueryParams,
                 body: bytes, content_type: str | None, accept: str | None) -> Response:
    """Interpolate field ``name`` at the flats of ``body``; the HTTP response."""
    t0 = time.perf_counter()
    if params.min_position is not None:
        await wait_position(registry, settings, params.min_position)
    e = registry.get(name)

    def decode():
        return codec.decode(body, content_type, params.form, k=e.spec.k, d=e.spec.d,
                            channels=None,
                            max_rows=settings.max_batch_rows,
                            max_json_bytes=settings.max_json_bytes)[0]

    if len(body) <= INLINE_BODY_BYTES:
        flats = decode()
    else:
        flats = await anyio.to_thread.run_sync(decode)
    kw = {"outside": params.outside, "order": params.order, "return_weights": params.weights}
    t1 = time.perf_counter()
    res = None
    if len(flats) < INLINE_ROWS and not params.wait:  # inline, unless an insert holds the field
        res = registry.query(e, flats, threads=1, blocking=False, **kw)
    if res is None:
        def run():
            if params.wait and not registry.wait_all_committed():
                raise NotReadyError(f"field {name!r}: the acknowledged batches are not "
                                    "indexed here yet (waited at most "
                                    f"{registry.settings.apply_wait_timeout:g} s, "
                                    "FLATSERVE_APPLY_WAIT_TIMEOUT, or the server is "
                                    "stopping); retry shortly")
            return registry.query(e, flats, **kw)

        res = await anyio.to_thread.run_sync(run)
    t2 = time.perf_counter()
    w = params.weights
    resp = codec.query_response(accept, res.values, res.inside, res.status,
                                res.ids if w else None, res.weights if w else None)
    resp.headers["Server-Timing"] = server_timing(
        {"decode": t1 - t0, "query": t2 - t1, "encode": time.perf_counter() - t2})
    return resp
