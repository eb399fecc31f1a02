"""The service's logging: one configuration for flatserve and uvicorn, and the access log.

* :func:`configure`: every record (flatserve's, uvicorn's) goes to one handler on
  stderr, as text (``time level logger[pid]: message``) or as one JSON object a
  line (``log_format = "json"``: ``time``, ``level``, ``logger``, ``pid``,
  ``message``, and the access fields below as members). The handler writes
  through :func:`tqdm.tqdm.write`, so a log line printed while a progress bar is
  drawn on the terminal (the demo field's) goes above the bar, which is redrawn.
* :class:`AccessLogMiddleware`: one line per request on the logger
  ``flatserve.access`` (``access_log``, on by default): method, route template,
  field, rows, status, milliseconds, request id (the client's ``X-Request-ID`` if
  it is a plain token, else a new one; sent back in ``X-Request-ID``). ``rows`` is
  noted by whoever decodes the batch (:func:`note`).
"""
from __future__ import annotations

import contextvars
import datetime as _dt
import logging
import re
import sys
import time
import uuid

import orjson

__all__ = ["configure", "AccessLogMiddleware", "note", "ACCESS_LOGGER", "LOG_FORMATS"]

ACCESS_LOGGER = "flatserve.access"
LOG_FORMATS = ("text", "json")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s"
REQUEST_ID_HEADER = b"x-request-id"
_TOKEN = re.compile(rb"^[A-Za-z0-9._:-]{1,128}$")
#: What the access log notes about the request being answered (see :func:`note`)
_NOTES: contextvars.ContextVar[dict | None] = contextvars.ContextVar("flatserve_access",
                                                                      default=None)
#: Attributes every LogRecord has: the rest are a record's ``extra`` members
_RECORD_ATTRS = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message",
                                                                               "asctime"}


def note(**fields) -> None:
    """Add ``fields`` (e.g. ``rows=n``) to the access-log line of the request being
    answered; nothing outside a request. Works from the thread pool too (its
    context is a copy that holds the same dictionary)."""
    notes = _NOTES.get()
    if notes is not None:
        notes.update(fields)


class TqdmHandler(logging.StreamHandler):
    """A stream handler that writes through ``tqdm.write`` (progress bars are
    cleared, the line written, the bars redrawn); plain writes without tqdm."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = self.format(record)
            try:
                from tqdm import tqdm
            except ImportError:  # pragma: no cover - the service extra has tqdm
                self.stream.write(msg + self.terminator)
                self.flush()
                return
            tqdm.write(msg, file=self.stream)
        except Exception:
            self.handleError(record)


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time (UTC, ISO 8601), level, logger, pid, message,
    the record's ``extra`` members, and ``exception`` (the traceback) if any."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"time": _dt.datetime.fromtimestamp(record.created, _dt.timezone.utc)
               .isoformat(timespec="milliseconds"),
               "level": record.levelname, "logger": record.name, "pid": record.process,
               "message": record.getMessage()}
        for k, v in vars(record).items():
            if k not in _RECORD_ATTRS and not k.startswith("_"):
                out[k] = v
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return orjson.dumps(out, default=str).decode()


def configure(level: str = "info", fmt: str = "text", stream=None) -> None:
    """The one logging configuration of a server process (flatserve and uvicorn).

    Parameters
    ----------
    level : str
        ``debug``, ``info``, ``warning``, ... (case-insensitive).
    fmt : {"text", "json"}
    stream : file, optional
        Where lines go (default stderr).
    """
    if fmt not in LOG_FORMATS:
        raise ValueError(f"log_format: one of {LOG_FORMATS}, got {fmt!r}")
    handler = TqdmHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in ("flatserve", "uvicorn", "uvicorn.error"):
        lg = logging.getLogger(name)
        lg.handlers.clear()
        lg.propagate = True
        lg.setLevel(level.upper())
    # uvicorn's own access log is off (it lacks route, field, rows): ours replaces it
    logging.getLogger("uvicorn.access").disabled = True


class AccessLogMiddleware:
    """Pure ASGI middleware, outermost: one ``flatserve.access`` line per HTTP request
    (see the module doc), the request id in ``X-Request-ID``."""

    def __init__(self, app):
        self.app = app
        self.log = logging.getLogger(ACCESS_LOGGER)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        rid = None
        for k, v in scope.get("headers", ()):
            if k == REQUEST_ID_HEADER and _TOKEN.match(v):
                rid = v.decode("ascii")
                break
        rid = rid or uuid.uuid4().hex[:16]
        notes: dict = {}
        token = _NOTES.set(notes)
        status = [500]

        async def sending(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
                msg = {**msg, "headers": [*msg.get("headers", ()),
                                          (REQUEST_ID_HEADER, rid.encode())]}
            await send(msg)

        try:
            await self.app(scope, receive, sending)
        finally:
            _NOTES.reset(token)
            route = getattr(scope.get("route"), "path", None) or scope.get("path", "")
            field = (scope.get("path_params") or {}).get("name") or notes.get("field")
            fields = {"method": scope["method"], "route": route, "field": field,
                      "rows": notes.get("rows"), "status": status[0],
                      "ms": round((time.perf_counter() - t0) * 1e3, 2), "request_id": rid}
            client = scope.get("client")
            if client:
                fields["client"] = client[0]
            text = " ".join(f"{k}={v}" for k, v in fields.items()
                            if v is not None and k not in ("method", "route", "status", "ms"))
            self.log.info("%s %s %d %.1f ms %s", fields["method"], route, status[0],
                          fields["ms"], text, extra=fields)
