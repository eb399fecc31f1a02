"""A lean ASGI path for ``POST /v1/fields/{name}/query`` (the hot endpoint).

The FastAPI route (:func:`flatserve.service.routes.query_field`) documents the
endpoint and stays the reference; this middleware answers the same requests
with the same code (:func:`codec.decode`, :meth:`Registry.query`,
:func:`codec.query_response`, :func:`errors.error_response`) but without
FastAPI's per-request machinery (dependency solving, parameter models, a
thread-pool hop per dependency and handler), which costs more than a small
query itself:

* small batches (< :data:`INLINE_ROWS` rows) run inline on the event loop on one
  native thread, when the field's read lock is free right away (never waiting
  on the loop: a running insert sends them to the thread pool);
* larger batches run in the thread pool (the C++ releases the GIL, so they
  run in parallel).

Anything unusual (bad or repeated query parameters, a missing or wrong API key,
other methods) is passed on untouched to FastAPI, so statuses and error bodies
stay exactly those of the route.
"""
from __future__ import annotations

import logging
import re
import time
from urllib.parse import parse_qsl

import anyio.to_thread

from . import codec, errors
from .registry import SMALL_QUERY_ROWS
from .settings import FIELD_NAME_PATTERN

log = logging.getLogger("flatserve.service")

#: queries with fewer rows run inline on the event loop (about 0.1-0.3 ms of CPU)
INLINE_ROWS = 64

QUERY_ROUTE = "/v1/fields/{name}/query"
_PATH = re.compile(r"^/v1/fields/(" + FIELD_NAME_PATTERN.strip("^$") + r")/query$")
_BOOL = {"true": True, "1": True, "yes": True, "on": True,
         "false": False, "0": False, "no": False, "off": False}
_CHOICES = {"form": codec.FORMS, "outside": ("nan", "clamp"), "order": ("hilbert", "given")}


def _params(qs: bytes) -> dict | None:
    """The route's query parameters, or None to let FastAPI handle (and judge) them."""
    out = {"form": None, "outside": "nan", "order": "hilbert", "weights": False, "wait": False}
    if not qs:
        return out
    seen = set()
    for k, v in parse_qsl(qs.decode("latin-1"), keep_blank_values=True):
        if k in seen or k not in out:
            return None
        seen.add(k)
        if k in _CHOICES:
            if v not in _CHOICES[k]:
                return None
            out[k] = v
        else:
            b = _BOOL.get(v.lower())
            if b is None:
                return None
            out[k] = b
    return out


class FastQueryMiddleware:
    """Answers ``POST /v1/fields/{name}/query`` directly (see the module doc)."""

    def __init__(self, app, fastapi_app):
        self.app = app
        self.fastapi_app = fastapi_app
        self._route = None

    def _route_obj(self):
        if self._route is None:
            from .routes import api

            for r in api.routes:
                if getattr(r, "path", None) == QUERY_ROUTE:
                    self._route = r
                    break
        return self._route

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "POST":
            return await self.app(scope, receive, send)
        m = _PATH.match(scope["path"])
        if m is None:
            return await self.app(scope, receive, send)
        params = _params(scope.get("query_string", b""))
        state = self.fastapi_app.state
        registry = getattr(state, "registry", None)
        if params is None or registry is None:
            return await self.app(scope, receive, send)
        headers = dict(scope["headers"])  # later duplicates win; none expected here
        settings = state.settings
        if settings.auth_enabled and not _authorised(headers, settings):
            return await self.app(scope, receive, send)  # FastAPI answers 401
        scope["route"] = self._route_obj()  # the metrics label: the route template
        try:
            resp = await self._query(m.group(1), params, headers, receive, registry, settings)
        except Exception as exc:
            status = errors.status_of(exc)
            if status >= 500:
                log.error("POST %s failed: %s", scope["path"], exc, exc_info=status == 500)
            resp = errors.error_response(exc)
        await resp(scope, receive, send)

    async def _query(self, name, params, headers, receive, registry, settings):
        t0 = time.perf_counter()
        body = await _read_body(receive, settings.max_body_bytes)
        e = registry.get(name)
        t1 = time.perf_counter()
        ctype = headers.get(b"content-type")
        form, arrays, _, _ = codec.decode(
            body, ctype.decode("latin-1") if ctype is not None else None, params["form"],
            k=e.k, d=e.d, channels=None, max_rows=settings.max_batch_rows)
        n = len(next(iter(arrays.values())))
        kw = {"outside": params["outside"], "order": params["order"],
              "return_weights": params["weights"]}
        t2 = time.perf_counter()
        res = None
        if n < INLINE_ROWS and not params["wait"]:
            res = registry.query_nowait(e, form, arrays, threads=1, **kw)
        if res is None:
            if n < SMALL_QUERY_ROWS:
                kw["threads"] = 1

            def run():
                if params["wait"]:
                    registry.wait_indexed(e)
                return registry.query(e, form, arrays, **kw)

            res = await anyio.to_thread.run_sync(run)
        t3 = time.perf_counter()
        accept = headers.get(b"accept")
        w = params["weights"]
        resp = codec.query_response(accept.decode("latin-1") if accept is not None else None,
                                    res.values, res.inside, res.status,
                                    res.ids if w else None, res.weights if w else None)
        resp.headers["Server-Timing"] = (
            f"decode;dur={(t2 - t1 + t1 - t0) * 1e3:.3f}, query;dur={(t3 - t2) * 1e3:.3f}, "
            f"encode;dur={(time.perf_counter() - t3) * 1e3:.3f}")
        return resp


async def _read_body(receive, limit: int) -> bytes:
    chunks, n = [], 0
    while True:
        msg = await receive()
        if msg["type"] == "http.disconnect":
            raise errors.ApiError(400, "client disconnected")
        chunk = msg.get("body", b"")
        if chunk:
            n += len(chunk)
            if n > limit:
                raise errors.BodyTooLargeError(f"body exceeds the limit of {limit} bytes")
            chunks.append(chunk)
        if not msg.get("more_body", False):
            return chunks[0] if len(chunks) == 1 else b"".join(chunks)


def _authorised(headers: dict, settings) -> bool:
    from .deps import _eq

    key = headers.get(b"api-key")
    if key:
        key = key.decode("latin-1")
    else:
        auth = headers.get(b"authorization", b"").decode("latin-1")
        scheme, _, cred = auth.partition(" ")
        if scheme.lower() != "bearer" or not cred:
            return False
        key = cred
    return _eq(key, settings.api_key) or _eq(key, settings.read_only_key)
