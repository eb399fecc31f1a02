"""Where exceptions become HTTP responses.

The library raises :mod:`flatserve.errors` and the service :mod:`..status`, whose
``HTTP_STATUS`` table gives the status; the service raises :class:`ApiError` for HTTP-only conditions
(content type, auth). Bad input is always a 4xx: a 422 names the offending
argument in ``detail[].loc`` (FastAPI's ``HTTPValidationError`` shape, so it
matches the documented schema).
"""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from .responses import JSONBytes as ORJSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from ...errors import FlatserveError
from .. import status as st
log = logging.getLogger("flatserve.service")


class ApiError(Exception):
    """An HTTP-level refusal raised by the service itself."""

    def __init__(self, status: int, detail: str, *, argument: str | None = None,
                 headers: dict[str, str] | None = None):
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.argument = argument
        self.headers = headers


class ErrorBody(BaseModel):
    """Body of every non-422 error response."""

    detail: str


# Documented on every route (OpenAPI); 422 is FastAPI's HTTPValidationError.
#: what flatserve.service.http.guard refuses on every route (forged cross-site requests)
GUARD_RESPONSES: dict[int | str, dict] = {
    400: {"model": ErrorBody, "description": "A header that must be sent once is repeated, "
                                             "or `api-key` and `Authorization: Bearer` "
                                             "carry different keys."},
    403: {"model": ErrorBody, "description": "A cross-origin request from an origin not "
                                             "allowed (or the read-only key for a write)."},
    415: {"model": ErrorBody, "description": "A Content-Type this route does not take."},
    421: {"model": ErrorBody, "description": "A Host this server does not serve."},
}
COMMON_RESPONSES: dict[int | str, dict] = {
    **GUARD_RESPONSES,
    401: {"model": ErrorBody, "description": "Missing or wrong API key."},
    408: {"description": "The request's headers or body arrived too slowly (`header_timeout`, "
                         "`body_timeout`, `body_min_rate`); the connection is closed."},
    413: {"model": ErrorBody, "description": "Body or batch too large."},
    503: {"model": ErrorBody, "description": "Stored fields are still loading, or storage failed."},
}
FIELD_RESPONSES: dict[int | str, dict] = {
    **COMMON_RESPONSES,
    404: {"model": ErrorBody, "description": "No field with this name."},
}
BODY_RESPONSES: dict[int | str, dict] = {
    **FIELD_RESPONSES,
    409: {"model": ErrorBody, "description": "Conflict (existing name, field limit)."},
}
#: A write (create, delete, upload, snapshot) on a full disk
_DISK_FULL = {507: {"model": ErrorBody, "description": "The disk is full: nothing was stored; "
                                                      "retry after `Retry-After` seconds "
                                                      "(reads go on)."}}
WRITE_RESPONSES: dict[int | str, dict] = {**BODY_RESPONSES, **_DISK_FULL}
FIELD_WRITE_RESPONSES: dict[int | str, dict] = {**FIELD_RESPONSES, **_DISK_FULL}
UPLOAD_RESPONSES: dict[int | str, dict] = {
    **WRITE_RESPONSES,
    429: {"model": ErrorBody, "description": "`wait=false`: `max_pending_samples` acknowledged "
                                             "samples of the field wait for their insert; "
                                             "retry after `Retry-After` seconds."},
}


def status_of(exc: BaseException) -> int:
    """HTTP status of an exception: :class:`ApiError`'s own, else the library table.

    See :data:`flatserve.service.status.HTTP_STATUS`.
    """
    if isinstance(exc, ApiError):
        return exc.status
    return st.status_of(exc)


def _message(exc: BaseException) -> str:
    """What a client is told: an error's ``public`` text if it has one (storage
    failures: their full text, for the log, names the database's host and files)."""
    public = getattr(exc, "public", None)
    if public:
        return public
    if isinstance(exc, MemoryError):
        return ("out of memory: the server could not finish this request now (a write is "
                "not stored); retry later, or with fewer rows at a time")
    if isinstance(exc, KeyError) and exc.args:
        return str(exc.args[0])
    return str(exc) or type(exc).__name__


def error_response(exc: BaseException) -> ORJSONResponse:
    status = status_of(exc)
    msg = _message(exc)
    headers = getattr(exc, "headers", None)
    if (status == 503 and isinstance(exc, (st.NotReadyError, st.StorageUnavailableError,
                                           MemoryError))
            or status in (429, 507)):
        headers = {**(headers or {}), "Retry-After": "1"}
    if status == 422:
        arg = getattr(exc, "argument", None)
        where = getattr(exc, "location", "body")  # "query" for query parameters
        loc = [where, *arg.split(".")] if arg else [where]  # "basis.center.A" -> path
        body = {"detail": [{"loc": loc, "msg": msg, "type": type(exc).__name__}]}
    else:
        body = {"detail": msg}
    return ORJSONResponse(body, status_code=status, headers=headers)


def log_failure(method: str, path: str, exc: BaseException, status: int) -> None:
    """Log a 5xx: a bug (500) at ERROR with its traceback; the expected refusals of
    a server that works (503 while a field loads, 507 on a full disk) at WARNING."""
    if status == 500:
        log.error("%s %s failed: %s", method, path, exc, exc_info=exc)
    else:
        log.warning("%s %s: %d %s", method, path, status, exc)


def allowed_methods(request: Request) -> list[str]:
    """The methods of every route whose path matches the request's (Starlette's 405
    names only the first such route's); the routes are those :func:`install` was
    given."""
    path = request.scope["path"]
    return sorted({m for regex, methods in request.app.state.route_methods
                   if regex.match(path) for m in methods})


def install(app: FastAPI, routers=()) -> None:
    """Register the handlers on ``app``; ``routers``: the routers it includes, whose
    routes' methods (and those of the app's own routes: the docs) a 405 lists in
    ``Allow``."""
    routes = [r for router in (app.router, *routers) for r in router.routes]
    app.state.route_methods = [(r.path_regex, frozenset(r.methods)) for r in routes
                               if getattr(r, "methods", None) and hasattr(r, "path_regex")]

    async def _handle(request: Request, exc: Exception):
        status = status_of(exc)
        if status >= 500:
            log_failure(request.method, request.url.path, exc, status)
        elif isinstance(exc, ValueError) and not isinstance(exc, FlatserveError):
            log.warning("%s %s: unclassified ValueError mapped to 422: %s",
                        request.method, request.url.path, exc)
        return error_response(exc)

    for cls in (ApiError, FlatserveError, ValueError, MemoryError):
        app.add_exception_handler(cls, _handle)

    async def _validation(request: Request, exc: RequestValidationError):
        # FastAPI's own format, orjson'd; input values can be non-JSON bytes.
        errs = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")),
                 "type": str(e.get("type", ""))} for e in exc.errors()]
        return ORJSONResponse({"detail": errs}, status_code=422)

    app.add_exception_handler(RequestValidationError, _validation)

    async def _http(request: Request, exc: StarletteHTTPException):
        cause = exc.__cause__
        if isinstance(cause, (ApiError, FlatserveError)):  # raised while FastAPI read the body
            return error_response(cause)
        if exc.status_code == 400:  # FastAPI could not decode the body: same shape as a 422
            return ORJSONResponse({"detail": [{"loc": ["body"], "msg": str(exc.detail),
                                               "type": "body_decode_error"}]}, status_code=422)
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # every method of the path, not one route's
            headers = {**(headers or {}), "Allow": ", ".join(allowed_methods(request))}
        return ORJSONResponse({"detail": str(exc.detail)}, status_code=exc.status_code,
                              headers=headers)

    app.add_exception_handler(StarletteHTTPException, _http)
