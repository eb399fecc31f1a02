"""flatserve's HTTP service (FastAPI). HTTP only: the math lives in flatserve.

The names below are imported on first use, so that :mod:`.status` (the
service's errors and their HTTP statuses, which :mod:`flatserve.client` shares)
imports without FastAPI.
"""
from __future__ import annotations

__all__ = ["create_app", "Settings", "serve"]


def __getattr__(name: str):
    if name == "create_app":
        from .app import create_app

        return create_app
    if name == "Settings":
        from .settings import Settings

        return Settings
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def serve(settings=None) -> None:
    from .server import serve as _serve

    _serve(settings)
