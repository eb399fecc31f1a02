"""``create_app(settings)``: the FastAPI application; state is built in ``lifespan``."""
from __future__ import annotations

import logging
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI

from .. import __version__
from .status import BodyTooLargeError
from .http import docs, errors
from .http.fastpath import FastQueryMiddleware
from .logs import AccessLogMiddleware
from .http.guard import RequestGuardMiddleware
from .http.metrics import Metrics, MetricsMiddleware
from .assembly import Rooms
from .http.routes import api, health
from .settings import Settings

log = logging.getLogger("flatserve.service")

DESCRIPTION = """\
Named **fields** of samples over affine subspaces (flats): a basis, a Delaunay
triangulation of the samples' coordinates, and values interpolated at query
flats. Bulk arrays travel as `application/x-npy` / `application/x-npz`; JSON is
for small requests. Uploads are acknowledged only once durably stored.
"""


class BodyLimitMiddleware:
    """The one body-size limit, for every route: 413 before reading anything when
    ``Content-Length`` exceeds it, and as soon as the bytes received pass it
    (chunked bodies have no length): ``receive`` is wrapped to count them and
    raises :class:`~.status.BodyTooLargeError`, which every reader of the body
    turns into a 413."""

    def __init__(self, app, limit: int):
        self.app = app
        self.limit = limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit = self.limit
        for k, v in scope.get("headers", ()):
            if k == b"content-length":
                if v.isdigit() and int(v) > limit:
                    resp = errors.error_response(BodyTooLargeError(
                        f"body of {int(v)} bytes exceeds the limit of {limit} bytes"))
                    return await resp(scope, receive, send)
                break
        seen = 0

        async def counted():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > limit:
                    raise BodyTooLargeError(f"body exceeds the limit of {limit} bytes")
            return msg

        started = False

        async def sending(msg):
            nonlocal started
            started = started or msg["type"] == "http.response.start"
            await send(msg)

        try:
            await self.app(scope, counted, sending)
        except BodyTooLargeError as exc:  # raised where no handler turned it into a 413
            if started:
                raise
            await errors.error_response(exc)(scope, receive, send)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Several clients (TestClient, schemathesis) may run the lifespan of one app at
        # once: the first builds the state, the last one out closes it.
        st = app.state
        st.lifespans = getattr(st, "lifespans", 0) + 1
        if st.lifespans == 1:
            _start(app, settings)
        try:
            yield
        finally:
            st.lifespans -= 1
            if st.lifespans == 0:
                _stop(app)

    app = FastAPI(title="flatserve", version=__version__, description=DESCRIPTION,
                  lifespan=lifespan, docs_url=None, redoc_url=None)
    docs.install(app)  # /docs and /redoc with their assets served here (no CDN)
    app.openapi = _openapi(app)
    app.state.settings = settings
    app.state.metrics = Metrics(replica=settings.replica)
    app.state.metrics.watch(_EntriesOf(app))
    from .http.routes_lightfield import lightfield_api, viewer  # light-field render + viewer page
    routers = (api, health, lightfield_api, viewer)
    errors.install(app, routers)
    for router in routers:
        app.include_router(router)
    app.add_middleware(FastQueryMiddleware, fastapi_app=app)  # innermost: metrics see it
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    app.add_middleware(RequestGuardMiddleware, settings=settings)
    if settings.access_log:  # outermost: it times and sees every answer (the guard's too)
        app.add_middleware(AccessLogMiddleware)
    return app


def app_ready(app: FastAPI) -> bool:
    """The app's stored fields are restored and it follows the log (``/readyz`` 200;
    a field that failed does not count against it)."""
    rooms = getattr(app.state, "rooms", None)
    return rooms is not None and rooms.catalogue.ready.is_set() and \
        rooms.follower.started.is_set()


def _openapi(app: FastAPI):
    """FastAPI's OpenAPI document plus the models of the JSON bodies parsed off the
    event loop (:func:`.http.deps.json_body`), under ``components/schemas`` as FastAPI
    would have put them."""
    from fastapi.openapi.utils import get_openapi

    from .http.deps import JSON_BODY_MODELS

    def openapi() -> dict:
        if app.openapi_schema is None:
            doc = get_openapi(title=app.title, version=app.version,
                              description=app.description, routes=app.routes)
            comps = doc.setdefault("components", {}).setdefault("schemas", {})
            for model in JSON_BODY_MODELS:
                js = model.model_json_schema(ref_template="#/components/schemas/{model}")
                for name, sub in js.pop("$defs", {}).items():
                    comps.setdefault(name, sub)
                comps.setdefault(model.__name__, js)
            app.openapi_schema = docs.hoist_defs(doc)
        return app.openapi_schema

    return openapi


def _start(app: FastAPI, settings: Settings) -> None:
    anyio.to_thread.current_default_thread_limiter().total_tokens = settings.workers
    rooms = Rooms.open(settings, app.state.metrics)
    app.state.rooms = rooms
    if not settings.auth_enabled:
        log.warning("no API key set: no authentication; listen on loopback only "
                    "(set FLATSERVE_API_KEY to serve other hosts)")
    rooms.start()
    if settings.demo:
        from .demo import start_demo_field

        start_demo_field(rooms, settings.bind_host(), settings.port)


def _stop(app: FastAPI) -> None:
    app.state.rooms.close()
    del app.state.rooms


class _EntriesOf:
    """What the metrics read at scrape time: the fields, and the log's lag."""

    def __init__(self, app):
        self.app = app

    def snapshot_entries(self):
        rooms = getattr(self.app.state, "rooms", None)
        return rooms.catalogue.entries() if rooms is not None else []

    def lag(self) -> dict | None:
        """This replica's log position, the head and the lag (None before it follows)."""
        rooms = getattr(self.app.state, "rooms", None)
        if rooms is None or not rooms.follower.started.is_set():
            return None
        try:
            return rooms.follower.lag()
        except Exception:  # the database is unreachable: no figures this scrape
            return None
