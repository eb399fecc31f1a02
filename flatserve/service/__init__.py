"""flatserve's HTTP service (FastAPI). HTTP only: the math lives in flatserve."""
from .app import create_app
from .settings import Settings

__all__ = ["create_app", "Settings", "serve"]


def serve(settings: Settings | None = None) -> None:
    from .server import serve as _serve

    _serve(settings)
