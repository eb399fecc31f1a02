"""``/docs`` (Swagger UI) and ``/redoc`` without a network: their scripts and styles
are served by this server from the assets the ``fastapi-offline`` package ships
(Swagger UI 5, ReDoc 2), under ``/docs/assets/``, never from a CDN; and
:func:`hoist_defs`, which keeps the OpenAPI document they show free of dangling
references."""
from __future__ import annotations

import html
from pathlib import Path
from typing import Callable

import fastapi_offline
from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["ASSETS", "ASSETS_URL", "COMPONENTS", "hoist_defs", "install"]

#: The package's static files: swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js
ASSETS = Path(fastapi_offline.__file__).parent / "static"
ASSETS_URL = "/docs/assets"
#: Where the OpenAPI document keeps its named schemas (a ``$ref`` prefix)
COMPONENTS = "#/components/schemas/"
#: The ``$ref`` prefix of a pydantic model's own definitions (``model_json_schema()``)
_DEFS = "#/$defs/"


def hoist_defs(doc: dict) -> dict:
    """Move the ``$defs`` of the schemas embedded in an OpenAPI document (a
    pydantic model's ``model_json_schema()`` given to a route's
    ``openapi_extra``) to ``components/schemas`` and point their ``#/$defs/``
    references there: resolved against the document's root, as OpenAPI does, such
    a reference names nothing. A definition whose name is taken already (by a
    component, or by another embedded schema's definition) must be the same schema
    (once its references point at the components): it is then kept once.

    Parameters
    ----------
    doc : dict
        The OpenAPI document; changed in place.

    Returns
    -------
    dict
        ``doc``.

    Raises
    ------
    ValueError
        Two different schemas under one name (naming it): one of them would be
        lost and the references to it would describe the other.
    """
    found: dict[str, dict] = {}

    def keep(name: str, sub: dict, taken: dict[str, dict], where: str) -> None:
        if name not in taken:
            taken[name] = sub
        elif taken[name] != sub:
            raise ValueError(
                f"OpenAPI schema {name!r}: an embedded model's $defs entry differs from "
                f"the {where} of that name (two models under one name)")

    def walk(node) -> None:
        if isinstance(node, dict):
            defs = node.pop("$defs", None) if isinstance(node.get("$defs"), dict) else None
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith(_DEFS):
                node["$ref"] = COMPONENTS + ref[len(_DEFS):]
            for value in node.values():
                walk(value)
            for name, sub in (defs or {}).items():
                walk(sub)
                keep(name, sub, found, "$defs entry of another embedded model")
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(doc)
    comps = doc.setdefault("components", {}).setdefault("schemas", {})
    for name, sub in found.items():
        keep(name, sub, comps, "component")
    return doc


#: The field the demo server makes (``flatserve serve --demo``; :data:`flatserve.service.demo.DEMO_FIELD`),
#: for the home page's viewer link.
DEMO_VIEWER_FIELD = "bunny"
#: ``GET /``: where to go from the server's root (no field names: listing them needs a key).
HOME_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title></head>
<body>
<h1>{title}</h1>
<p>Values sampled on flats (points, lines, planes) interpolated over a Delaunay
triangulation of their coordinates in an affine basis.</p>
<ul>
<li><a href="{root}/docs">API documentation</a> (Swagger UI; <a href="{root}/redoc">ReDoc</a>,
<a href="{root}/openapi.json">the OpenAPI schema</a>)</li>
<li><a href="{root}/v1/fields">The fields</a> (JSON; with the read key when one is set)</li>
<li><a href="{root}/v1/limits">The limits</a> of this server (JSON)</li>
<li><a href="{root}/viewer/{demo}">The light-field viewer</a> of the demo field
(<code>{root}/viewer/&lt;field&gt;</code> for another)</li>
<li><a href="{root}/healthz">Health</a>, <a href="{root}/readyz">readiness</a>,
<a href="{root}/metrics">metrics</a></li>
</ul>
</body></html>
"""


def install(app: FastAPI) -> None:
    """Serve ``/`` (a page of links: :data:`HOME_PAGE`), ``/docs``, ``/redoc`` and their
    assets on ``app`` (created with ``docs_url=None, redoc_url=None``)."""
    app.mount(ASSETS_URL, StaticFiles(directory=ASSETS), name="docs-assets")
    pages = APIRouter(include_in_schema=False)

    def urls(request: Request) -> tuple[str, Callable[[str], str]]:
        root = request.scope.get("root_path", "")
        return f"{root}{app.openapi_url}", lambda name: f"{root}{ASSETS_URL}/{name}"

    @pages.get("/docs", response_class=HTMLResponse)
    def swagger(request: Request) -> HTMLResponse:
        spec, asset = urls(request)
        return get_swagger_ui_html(
            openapi_url=spec, title=f"{app.title} - Swagger UI",
            swagger_js_url=asset("swagger-ui-bundle.js"), swagger_css_url=asset("swagger-ui.css"),
            swagger_favicon_url=asset("favicon.png"), swagger_ui_parameters=app.swagger_ui_parameters)

    @pages.get("/", response_class=HTMLResponse)
    def home(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return HTMLResponse(HOME_PAGE.format(root=html.escape(root, quote=True),
                                             title=html.escape(app.title),
                                             demo=DEMO_VIEWER_FIELD),
                            headers={"Cache-Control": "no-cache"})

    @pages.get("/redoc", response_class=HTMLResponse)
    def redoc(request: Request) -> HTMLResponse:
        spec, asset = urls(request)
        return get_redoc_html(openapi_url=spec, title=f"{app.title} - ReDoc",
                              redoc_js_url=asset("redoc.standalone.js"),
                              redoc_favicon_url=asset("favicon.png"), with_google_fonts=False)

    app.include_router(pages)
