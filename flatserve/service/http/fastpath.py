"""A lean ASGI path for ``POST /v1/fields/{name}/query`` (the hot endpoint).

It answers with the endpoint's one implementation (:func:`.query.answer`) but
without FastAPI's per-request machinery (dependency solving, a thread-pool hop
per dependency and handler), which costs more than a small query itself. Its
query string is validated by the route's own model (:class:`.query.QueryParams`);
anything unusual (parameters the model refuses, repeated parameters, other
methods) is passed on untouched to FastAPI, so statuses and error bodies stay
exactly those of the route. Keys are checked by the same function as the
routes' (:func:`.deps.authorize`).
"""
from __future__ import annotations

import logging
import re
from urllib.parse import parse_qsl

from pydantic import ValidationError

from . import errors
from .deps import authorize, presented_key, read_body
from .query import QueryParams, answer
from ..settings import FIELD_NAME_PATTERN

log = logging.getLogger("flatserve.service")

QUERY_ROUTE = "/v1/fields/{name}/query"
#: the route's path, matched whole (fullmatch: "$" alone would let a trailing newline in)
_PATH = re.compile(r"/v1/fields/(" + FIELD_NAME_PATTERN.strip("^$") + r")/query")
_NO_PARAMS = QueryParams()


def parse_params(qs: bytes) -> QueryParams | None:
    """The route's query parameters, or None to let FastAPI handle (and judge) them."""
    if not qs:
        return _NO_PARAMS
    out: dict = {}
    for k, v in parse_qsl(qs.decode("latin-1"), keep_blank_values=True):
        if k in out or k not in QueryParams.model_fields:
            return None
        out[k] = v
    try:
        return QueryParams.model_validate(out)
    except ValidationError:
        return None


class FastQueryMiddleware:
    """Answers ``POST /v1/fields/{name}/query`` directly (see the module doc)."""

    def __init__(self, app, fastapi_app):
        self.app = app
        self.fastapi_app = fastapi_app
        self._route = None

    def _route_obj(self):
        if self._route is None:
            from .routes import api

            self._route = next((r for r in api.routes
                                if getattr(r, "path", None) == QUERY_ROUTE), None)
        return self._route

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "POST":
            return await self.app(scope, receive, send)
        m = _PATH.fullmatch(scope["path"])
        if m is None:
            return await self.app(scope, receive, send)
        params = parse_params(scope.get("query_string", b""))
        state = self.fastapi_app.state
        rooms = getattr(state, "rooms", None)
        if params is None or rooms is None:
            return await self.app(scope, receive, send)
        headers = scope["headers"]
        scope["route"] = self._route_obj()  # the metrics label: the route template
        scope["path_params"] = {"name": m.group(1)}  # the access log's field
        try:
            authorize(state.settings, presented_key(headers), write=False)
            body = await read_body(receive)
            ctype = _header(headers, b"content-type")
            accept = _header(headers, b"accept")
            resp = await answer(rooms.queries, m.group(1), params, body, ctype, accept)
        except Exception as exc:
            status = errors.status_of(exc)
            if status >= 500:
                errors.log_failure("POST", scope["path"], exc, status)
            resp = errors.error_response(exc)
        await resp(scope, receive, send)


def _header(headers, name: bytes) -> str | None:
    for k, v in headers:
        if k == name:
            return v.decode("latin-1")
    return None
