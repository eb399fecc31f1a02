"""``/docs`` (Swagger UI) and ``/redoc`` without a network: their scripts and styles
are served by this server from the assets the ``fastapi-offline`` package ships
(Swagger UI 5, ReDoc 2), under ``/docs/assets/``, never from a CDN."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import fastapi_offline
from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["ASSETS", "ASSETS_URL", "install"]

#: The package's static files: swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js
ASSETS = Path(fastapi_offline.__file__).parent / "static"
ASSETS_URL = "/docs/assets"


def install(app: FastAPI) -> None:
    """Serve ``/docs``, ``/redoc`` and their assets on ``app`` (created with
    ``docs_url=None, redoc_url=None``)."""
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

    @pages.get("/redoc", response_class=HTMLResponse)
    def redoc(request: Request) -> HTMLResponse:
        spec, asset = urls(request)
        return get_redoc_html(openapi_url=spec, title=f"{app.title} - ReDoc",
                              redoc_js_url=asset("redoc.standalone.js"),
                              redoc_favicon_url=asset("favicon.png"), with_google_fonts=False)

    app.include_router(pages)
