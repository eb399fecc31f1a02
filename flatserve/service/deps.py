"""FastAPI dependencies (``Annotated`` aliases): state, body, API keys.

All are ``async def``: they never block, and FastAPI would run a plain ``def``
dependency in the thread pool (one thread hop per dependency per request).
"""
from __future__ import annotations

import secrets
from typing import Annotated, Optional

from fastapi import Depends, Path, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from .errors import ApiError, BodyTooLargeError
from .registry import Registry
from .settings import FIELD_NAME_PATTERN, Settings

_api_key_header = APIKeyHeader(name="api-key", auto_error=False,
                               description="API key (read-write or read-only).")
_bearer = HTTPBearer(auto_error=False, description="API key as `Authorization: Bearer <key>`.")


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_registry(request: Request) -> Registry:
    return request.app.state.registry


SettingsDep = Annotated[Settings, Depends(get_settings)]
RegistryDep = Annotated[Registry, Depends(get_registry)]
FieldNamePath = Annotated[str, Path(pattern=FIELD_NAME_PATTERN, description="Field name.")]


async def read_body(request: Request, settings: SettingsDep) -> bytes:
    """The request body, refused with 413 as soon as it exceeds ``max_body_bytes``."""
    limit = settings.max_body_bytes
    cl = request.headers.get("content-length")
    if cl is not None and cl.isdigit() and int(cl) > limit:
        raise BodyTooLargeError(f"body of {cl} bytes exceeds the limit of {limit} bytes")
    chunks, n = [], 0
    async for chunk in request.stream():
        n += len(chunk)
        if n > limit:
            raise BodyTooLargeError(f"body exceeds the limit of {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


BodyDep = Annotated[bytes, Depends(read_body)]


def _presented(api_key: Optional[str], bearer: Optional[HTTPAuthorizationCredentials]) -> Optional[str]:
    if api_key:
        return api_key
    if bearer is not None and bearer.credentials:
        return bearer.credentials
    return None


def _eq(a: str, secret) -> bool:
    return secret is not None and secrets.compare_digest(a.encode(), secret.get_secret_value().encode())


def _required_key(settings, api_key, bearer) -> Optional[str]:
    """The presented key, or None when authentication is off; 401 when missing."""
    if not settings.auth_enabled:
        return None
    key = _presented(api_key, bearer)
    if key is None:
        raise ApiError(401, "missing API key (header `api-key` or `Authorization: Bearer`)",
                       headers={"WWW-Authenticate": "Bearer"})
    return key


async def require_read(
    settings: SettingsDep,
    api_key: Annotated[Optional[str], Security(_api_key_header)] = None,
    bearer: Annotated[Optional[HTTPAuthorizationCredentials], Security(_bearer)] = None,
) -> None:
    key = _required_key(settings, api_key, bearer)
    if key is None or _eq(key, settings.api_key) or _eq(key, settings.read_only_key):
        return
    raise ApiError(401, "wrong API key", headers={"WWW-Authenticate": "Bearer"})


async def require_write(
    settings: SettingsDep,
    api_key: Annotated[Optional[str], Security(_api_key_header)] = None,
    bearer: Annotated[Optional[HTTPAuthorizationCredentials], Security(_bearer)] = None,
) -> None:
    key = _required_key(settings, api_key, bearer)
    if key is None or _eq(key, settings.api_key):
        return
    if _eq(key, settings.read_only_key):
        raise ApiError(403, "the read-only key cannot change data")
    raise ApiError(401, "wrong API key", headers={"WWW-Authenticate": "Bearer"})


ReadAccess = Depends(require_read)
WriteAccess = Depends(require_write)
