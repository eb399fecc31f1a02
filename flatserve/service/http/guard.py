"""Requests a browser can forge, refused before any route runs.

A web page the user visits can make the browser send requests to this server
(a form, ``fetch`` in ``no-cors`` mode) without asking it first, and a page
whose name is made to resolve to 127.0.0.1 (DNS rebinding) can read the answers
as its own. Without an API key (the default, on loopback) nothing else would
stop them. :class:`RequestGuardMiddleware`, outermost, refuses:

* a ``Host`` header not in the allow-list (:func:`allowed_hosts`): 421, the
  rebinding page's own name;
* an ``Origin`` header naming another origin than the request's own and not in
  ``cors_origins``: 403 (browsers send ``Origin`` on every cross-origin request
  but simple GETs, and on every POST);
* the three body types a page can send without a CORS preflight
  (:data:`SIMPLE_BODY_TYPES`, which no route takes): 415;
* a path with a control character (``%0A``...): 404, for every route alike
  (Python's ``$``, in Starlette's route patterns too, matches before a final
  newline: ``/v1/fields/f/query%0A`` would be the query route).

With ``cors_origins`` set, Starlette's ``CORSMiddleware`` (inside the guard)
answers preflights and adds the CORS headers for those origins; without it the
server sends no CORS headers, so no other site's page can read an answer.

Each route's own Content-Type check (415 for any type it does not take) is in
:func:`.deps.json_body`, :func:`.codec.body_kind` and :data:`.deps.NoBody`.
"""
from __future__ import annotations

import re

from . import errors
from .codec import media_type
from .errors import ApiError
from ..settings import Settings

#: Content-Types of a CORS "simple" request (sent cross-site without a preflight)
SIMPLE_BODY_TYPES = frozenset({"text/plain", "multipart/form-data",
                               "application/x-www-form-urlencoded"})
#: the names of this machine's loopback interface, always allowed by default
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
#: addresses that bind every interface: no Host can be known in advance
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
#: control characters, which no path of the service has
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
#: headers of the service a browser page may read with CORS on
EXPOSED_HEADERS = ["Flatserve-Position", "Server-Timing", "Retry-After", "X-Coverage",
                   "X-Render-Seconds", "X-Render"]


def allowed_hosts(settings: Settings) -> frozenset[str] | None:
    """The ``Host`` names accepted (lower case, no port), or None for any."""
    if settings.allowed_hosts:
        hosts = [h.lower().rstrip(".") for h in settings.allowed_hosts]
        return None if "*" in hosts else frozenset(h.strip("[]") for h in hosts)
    bound = settings.bind_host().lower()
    if bound in WILDCARD_HOSTS:
        return None
    return frozenset((bound.strip("[]"), *LOCAL_HOSTS))


def host_name(host: str) -> str:
    """The name of a ``Host`` header value: lower case, without port and brackets."""
    host = host.strip().lower()
    if host.startswith("["):  # [::1]:8000
        return host[1:].split("]", 1)[0]
    if host.count(":") == 1:
        host = host.split(":", 1)[0]
    return host.rstrip(".")


class RequestGuardMiddleware:
    """Refuses forged cross-site requests (see the module doc); outermost."""

    def __init__(self, app, settings: Settings):
        self.hosts = allowed_hosts(settings)
        self.origins = frozenset(settings.cors_origins)
        self.any_origin = "*" in self.origins
        if self.origins:
            from starlette.middleware.cors import CORSMiddleware

            app = CORSMiddleware(app, allow_origins=sorted(self.origins), allow_methods=["*"],
                                 allow_headers=["*"], expose_headers=EXPOSED_HEADERS)
        self.app = app

    def refusal(self, headers) -> ApiError | None:
        """Why a request with these raw ASGI headers is refused, or None."""
        host = origin = ctype = None
        for k, v in headers:
            if k == b"host":
                if host is not None:
                    return ApiError(400, "the Host header is repeated; send it once")
                host = v.decode("latin-1")
            elif k == b"origin":
                origin = v.decode("latin-1").strip().lower()
            elif k == b"content-type":
                ctype = media_type(v.decode("latin-1"))
        if host is not None and self.hosts is not None and host_name(host) not in self.hosts:
            return ApiError(421, f"Host {host_name(host)!r} is not served here (allowed: "
                                 f"{', '.join(sorted(self.hosts))}; FLATSERVE_ALLOWED_HOSTS)")
        if origin is not None and not self.any_origin and origin not in self.origins:
            own = origin.partition("://")[2]
            if host is None or own != host.strip().lower():
                return ApiError(403, f"cross-origin request from {origin!r} refused (allowed "
                                     "origins: FLATSERVE_CORS_ORIGINS)")
        if ctype in SIMPLE_BODY_TYPES:
            return ApiError(415, f"unsupported Content-Type {ctype!r}: no route takes it "
                                 "(application/json, application/x-npy or application/x-npz)")
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            exc = self.refusal(scope["headers"])
            if exc is None and _CONTROL.search(scope["path"]):
                exc = ApiError(404, "Not Found")
            if exc is not None:
                return await errors.error_response(exc)(scope, receive, send)
        return await self.app(scope, receive, send)
