"""FastAPI dependencies (``Annotated`` aliases): each room, the field of a path,
the body, API keys.

A route names the rooms it uses (``FieldsDep``, ``UploadsDep``, ``QueriesDep``,
``SnapshotsDep``, ``FollowerDep``, ``CatalogueDep``, ``TransferDep``); none reaches one room
through another.

All are ``async def``: they never block, and FastAPI would run a plain ``def``
dependency in the thread pool (one thread hop per dependency per request).
"""
from __future__ import annotations

import secrets
from typing import Annotated, Optional

from fastapi import Depends, Path, Request, Security
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from .codec import JSON, check_json_size, check_body, is_json, media_type
from .errors import ApiError
from ..rooms.catalogue import FieldCatalogue
from ..rooms.entry import FieldEntry
from ..rooms.fields import FieldService
from ..rooms.query import QueryService
from ..rooms.replica import Follower
from ..settings import FIELD_NAME_PATTERN, Settings
from ..rooms.snapshots import SnapshotWriter
from ..rooms.transfer import TransferService
from ..rooms.uploads import UploadService

_api_key_header = APIKeyHeader(name="api-key", auto_error=False,
                               description="API key (read-write or read-only).")
_bearer = HTTPBearer(auto_error=False, description="API key as `Authorization: Bearer <key>`.")


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def _room(name: str):
    """The dependency that gives the room ``name`` of this app's rooms."""
    async def get(request: Request):
        return getattr(request.app.state.rooms, name)

    get.__name__ = get.__qualname__ = f"get_{name}"
    return Depends(get)


SettingsDep = Annotated[Settings, Depends(get_settings)]
CatalogueDep = Annotated[FieldCatalogue, _room("catalogue")]
FieldsDep = Annotated[FieldService, _room("fields")]
UploadsDep = Annotated[UploadService, _room("uploads")]
QueriesDep = Annotated[QueryService, _room("queries")]
SnapshotsDep = Annotated[SnapshotWriter, _room("snapshots")]
FollowerDep = Annotated[Follower, _room("follower")]
TransferDep = Annotated[TransferService, _room("transfer")]
FieldNamePath = Annotated[str, Path(pattern=FIELD_NAME_PATTERN, description="Field name.")]


async def get_ready_field(name: FieldNamePath, catalogue: CatalogueDep) -> FieldEntry:
    """The field of the path, ready (404, or 503 while it loads or if it failed)."""
    return catalogue.get(name)


async def get_any_field(name: FieldNamePath, catalogue: CatalogueDep) -> FieldEntry:
    """The field of the path in whatever state (404 if there is none)."""
    return catalogue.get(name, need_ready=False)


ReadyField = Annotated[FieldEntry, Depends(get_ready_field)]
AnyField = Annotated[FieldEntry, Depends(get_any_field)]


async def read_body(receive) -> bytes:
    """The whole body from an ASGI ``receive`` (the size limit is enforced on
    ``receive`` itself by :class:`flatserve.service.app.BodyLimitMiddleware`)."""
    chunks = []
    while True:
        msg = await receive()
        if msg["type"] == "http.disconnect":
            raise ApiError(400, "client disconnected")
        chunk = msg.get("body", b"")
        if chunk:
            chunks.append(chunk)
        if not msg.get("more_body", False):
            return chunks[0] if len(chunks) == 1 else b"".join(chunks)


async def request_body(request: Request) -> bytes:
    return await request.body()


BodyDep = Annotated[bytes, Depends(request_body)]

#: JSON bodies parsed off the event loop (see :func:`json_body`); documented in OpenAPI
#: under ``components/schemas`` by :func:`flatserve.service.app.create_app`
JSON_BODY_MODELS: list[type[BaseModel]] = []


def json_body(model: type[BaseModel]):
    """``Annotated[model, ...]``: the request body validated as ``model`` in the
    thread pool (a plain ``def`` dependency), never on the event loop, with
    FastAPI's 422 format; pair it with :func:`json_body_doc` on the route."""
    def parse(request: Request, body: BodyDep, settings: SettingsDep) -> BaseModel:
        ctype = request.headers.get("content-type")
        if not is_json(ctype):
            raise ApiError(415, f"unsupported Content-Type {media_type(ctype)!r}: this route "
                                f"takes {JSON}" if ctype else f"a body needs a Content-Type: "
                                f"this route takes {JSON}")
        check_json_size(body, settings.max_json_bytes)
        check_body(body, "json")
        try:
            return model.model_validate_json(body)
        except ValidationError as exc:
            raise RequestValidationError(
                [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]
            ) from None

    JSON_BODY_MODELS.append(model)
    return Annotated[model, Depends(parse)]


def request_example(model: type[BaseModel]) -> dict:
    """The OpenAPI media-type members of ``model``'s request example (``example``:
    the first of its schema's ``examples``), or ``{}``."""
    examples = (model.model_config.get("json_schema_extra") or {}).get("examples")
    return {"example": examples[0]} if examples else {}


def json_body_doc(model: type[BaseModel]) -> dict:
    """``openapi_extra`` of a route whose body is read by :func:`json_body`."""
    return {"requestBody": {"required": True, "content": {"application/json": {
        "schema": {"$ref": f"#/components/schemas/{model.__name__}"},
        **request_example(model)}}},
        "responses": {"422": {"description": "Validation Error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/HTTPValidationError"}}}}}}


async def no_body(request: Request) -> None:
    """A route that takes no body refuses one (415), and any Content-Type: a form
    another site's page posts here is refused whatever its fields."""
    h = request.headers
    if "content-type" in h or h.get("content-length", "0") not in ("", "0") \
            or "transfer-encoding" in h:
        raise ApiError(415, "this route takes no body (and no Content-Type)")


#: the dependency of every route without a request body
NoBody = Depends(no_body)


def single_headers(headers, names: tuple[bytes, ...]) -> dict[bytes, bytes]:
    """The headers ``names`` (lower case) of raw ASGI ``headers``, each at most once:
    a repeated one is refused (400), since proxies and frameworks disagree on which
    copy counts (the first, the last, both joined)."""
    found: dict[bytes, bytes] = {}
    for k, v in headers:
        if k in names:
            if k in found:
                raise ApiError(400, f"the {k.decode()} header is repeated; send it once")
            found[k] = v
    return found


async def once_idempotency_key(request: Request) -> None:
    """400 for a repeated ``Idempotency-Key`` header (see :func:`single_headers`)."""
    single_headers(request.scope["headers"], (b"idempotency-key",))


#: the dependency of a route that takes an ``Idempotency-Key``
OnceIdempotencyKey = Depends(once_idempotency_key)


def presented_key(headers) -> Optional[str]:
    """The API key of a request (raw ASGI headers): header ``api-key`` or
    ``Authorization: Bearer``; None when neither. Repeated headers are refused
    (400, :func:`single_headers`), and so are two different keys in the two (400:
    neither is taken over the other, as a read-only key beside the read-write one
    must not write); the same key in both is that key."""
    found = single_headers(headers, (b"api-key", b"authorization"))
    scheme, _, cred = found.get(b"authorization", b"").decode("latin-1").partition(" ")
    bearer = cred.strip() if scheme.lower() == "bearer" and cred.strip() else None
    key = found.get(b"api-key", b"").decode("latin-1") or None
    if key is not None and bearer is not None and key != bearer:
        raise ApiError(400, "two different API keys: the `api-key` header and "
                            "`Authorization: Bearer`; send one key, in one of them")
    return key if key is not None else bearer


def _eq(a: str, secret) -> bool:
    """``a`` (a header value, decoded as latin-1) equals the configured key: compared as
    the bytes on the wire and the key's UTF-8 bytes, so non-ASCII keys work."""
    return secret is not None and secrets.compare_digest(
        a.encode("latin-1"), secret.get_secret_value().encode("utf-8"))


def authorize(settings: Settings, key: Optional[str], *, write: bool) -> None:
    """The one key check: raise 401 (missing or wrong key) or 403 (the read-only
    key for a write); nothing when keys are off or the key grants access."""
    if not settings.auth_enabled:
        return
    if key is None:
        raise ApiError(401, "missing API key (header `api-key` or `Authorization: Bearer`)",
                       headers={"WWW-Authenticate": "Bearer"})
    if _eq(key, settings.api_key):
        return
    if _eq(key, settings.read_only_key):
        if not write:
            return
        raise ApiError(403, "the read-only key cannot change data")
    raise ApiError(401, "wrong API key", headers={"WWW-Authenticate": "Bearer"})


def _access(write: bool):
    """The dependency that checks a request's key for reading or (``write``) writing.

    The Security parameters document the two ways of sending a key in OpenAPI; the
    key itself is read from the raw headers by presented_key (repeats refused)."""

    async def require(
        request: Request, settings: SettingsDep,
        api_key: Annotated[Optional[str], Security(_api_key_header)] = None,
        bearer: Annotated[Optional[HTTPAuthorizationCredentials], Security(_bearer)] = None,
    ) -> None:
        authorize(settings, presented_key(request.scope["headers"]), write=write)

    require.__name__ = require.__qualname__ = "require_write" if write else "require_read"
    return require


require_read = _access(write=False)
require_write = _access(write=True)
ReadAccess = Depends(require_read)
WriteAccess = Depends(require_write)
