"""Slow clients and too many connections, below the ASGI application.

uvicorn has a keep-alive timeout but no timeout on reading a request's headers
or its body, so a client that drips its headers a byte a second, never finishes
them, or sends a body at 10 bytes a second holds a connection (and its memory)
forever. :func:`guarded_protocol` returns a subclass of uvicorn's httptools
protocol (the fast one) that adds, per connection:

* a **header timeout**: the header block of a request must be complete within
  ``header_timeout`` seconds of the connection being opened or of the first
  byte of the request (after a response, uvicorn's keep-alive timeout closes an
  idle connection). When it expires the connection is closed, after a
  ``408 Request Timeout`` if part of a request had arrived.
* a **body timeout**: a request body must arrive within ``body_timeout``
  seconds of its headers plus one second per ``body_min_rate`` bytes received,
  so a client sending at least ``body_min_rate`` bytes a second always gets its
  body through, whatever its size, and a dripping one is cut off after about
  ``body_timeout`` seconds: ``408`` (``Connection: close``) if no response was
  started, then the connection is closed. Time during which the server itself
  does not read (its buffer full while the handler is busy) is not held
  against the client.
* a **connection cap**: beyond ``max_connections`` open connections, a new
  connection's requests are answered ``503`` (``Connection: close``) by
  uvicorn's own handler, while the connections already admitted keep working.
  (uvicorn's ``limit_concurrency`` would answer 503 on *every* connection once
  the limit is reached, healthy ones included.)

The timers are lazy: one ``call_later`` per connection, plus one when a body
or a later request's header block spans several reads; nothing is done per read
but counting its bytes.
"""
from __future__ import annotations

import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("flatserve.service")

#: seconds a connection beyond the cap has to send its request (answered 503)
OVER_CAP_HEADER_TIMEOUT = 1.0

#: file descriptors kept for the server's own files (database, snapshots, pipes)
FD_RESERVE = 64

_408 = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
        b"content-length: 15\r\nconnection: close\r\n\r\nRequest Timeout")


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with header / body timeouts and a connection cap.

    Configure it through :func:`guarded_protocol`, which sets the class attributes
    below on a subclass (uvicorn builds one protocol object per connection).

    Attributes
    ----------
    header_timeout : float
        Seconds to receive a request's header block.
    body_timeout : float
        Seconds to receive a request's body, plus one second per ``body_min_rate``
        bytes received.
    body_min_rate : float
        Bytes per second that always get a body through.
    max_connections : int or None
        Open connections beyond which new ones are answered 503 (None: no cap).
    """

    header_timeout: float = 10.0
    body_timeout: float = 60.0
    body_min_rate: float = 64 * 1024
    max_connections: int | None = None

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # The timers are lazy: armed when there is something to time and none is
        # armed, never cancelled while the connection lives; when one fires it
        # looks at the state and re-arms for what is left (no timer per request).
        self._header_timer = None
        self._body_timer = None
        #: the parser waits for a header block (none begun or one unfinished)
        self._want_headers = True
        #: bytes of the awaited header block have arrived
        self._partial = False
        #: no request has been read on this connection yet (its clock runs from the
        #: connection's opening)
        self._first = True
        self._header_start = 0.0
        self._header_wait = self.header_timeout
        #: a request's headers are complete but its body is not
        self._want_body = False
        self._body_start = 0.0
        self._body_bytes = 0

    # -- connection ------------------------------------------------------------
    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        cap = self.max_connections
        if cap is not None and len(self.connections) > cap:
            # uvicorn answers every request of this connection with 503 + close; one
            # that sends nothing is not kept (its file descriptor is scarce)
            self.limit_concurrency = 0
            self._header_wait = min(self.header_timeout, OVER_CAP_HEADER_TIMEOUT)
        self._header_start = self.loop.time()
        self._header_timer = self.loop.call_later(self._header_wait, self._header_expired)

    def connection_lost(self, exc) -> None:
        self._cancel_timers()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._want_headers and not self._partial:
            self._partial = True
            if not self._first:
                self._header_start = self.loop.time()
            if self._header_timer is None:
                self._header_timer = self.loop.call_later(self._header_wait,
                                                          self._header_expired)
        elif self._want_body:  # body bytes (and framing, when chunked) for the rate
            self._body_bytes += len(data)
        super().data_received(data)
        if self._want_body and self._body_timer is None and not self.transport.is_closing():
            self._body_timer = self.loop.call_later(self.body_timeout, self._body_check)

    # -- parser callbacks --------------------------------------------------------
    def on_headers_complete(self) -> None:
        self._want_headers = self._partial = self._first = False
        self._want_body = True
        self._body_start = self.loop.time()
        self._body_bytes = 0
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._want_body = False
        self._want_headers = True
        self._partial = False
        super().on_message_complete()

    # -- timers ----------------------------------------------------------------
    def _cancel_timers(self) -> None:
        for t in (self._header_timer, self._body_timer):
            if t is not None:
                t.cancel()
        self._header_timer = self._body_timer = None

    def _busy(self) -> bool:
        """A response is being computed (the client may wait, its next request too)."""
        return self.cycle is not None and not self.cycle.response_complete

    def _header_expired(self) -> None:
        self._header_timer = None
        if self.transport.is_closing() or not (
                self._want_headers and (self._partial or self._first)):
            return  # the next request's first byte arms it again
        now = self.loop.time()
        if self._busy():  # e.g. a pipelined request waiting behind a slow response
            self._header_start = now
        deadline = self._header_start + self._header_wait
        if now < deadline:
            self._header_timer = self.loop.call_later(deadline - now, self._header_expired)
            return
        if self._partial:
            log.info("%s: request headers not complete within %g s; connection closed",
                     _peer(self.client), self.header_timeout)
            self.transport.write(_408)
        self.transport.close()

    def _body_check(self) -> None:
        self._body_timer = None
        if self.transport.is_closing() or not self._want_body:
            return
        now = self.loop.time()
        if self.flow is not None and self.flow.read_paused:
            # the server is not reading (its buffer is full): the client is not late
            self._body_start, self._body_bytes = now, 0
            self._body_timer = self.loop.call_later(self.body_timeout, self._body_check)
            return
        deadline = self._body_start + self.body_timeout + self._body_bytes / self.body_min_rate
        if now < deadline:
            self._body_timer = self.loop.call_later(deadline - now, self._body_check)
            return
        log.warning("%s: request body too slow (%d bytes in %.1f s); connection closed",
                    _peer(self.client), self._body_bytes, now - self._body_start)
        cycle = self.cycle
        if cycle is not None and not cycle.response_started:
            self.transport.write(_408)
        if cycle is not None and not cycle.response_complete:
            cycle.disconnected = True  # the handler's receive() gets http.disconnect
            cycle.message_event.set()
        self.transport.close()


def _peer(client) -> str:
    return "%s:%d" % client if client else "client"


def connection_cap(requested: int) -> tuple[int | None, str | None]:
    """The connection cap this process can keep, and why it differs from ``requested``.

    Every connection holds a file descriptor, so the cap must stay below the
    open-files limit (``ulimit -n``) with :data:`FD_RESERVE` to spare for the
    server's own files. The soft limit is raised toward the hard one when needed;
    if that is not enough, the cap is lowered (half the limit when it is small).

    Parameters
    ----------
    requested : int
        ``max_connections`` (0: as many as the open-files limit allows).

    Returns
    -------
    cap : int or None
        None: no cap (no open-files limit).
    note : str or None
        Why the cap or the limit was changed, for the log.
    """
    try:
        import resource
    except ImportError:  # not a POSIX system
        return requested or None, None
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    inf = resource.RLIM_INFINITY
    note = None
    if requested and soft != inf and soft < requested + FD_RESERVE:
        target = requested + FD_RESERVE if hard == inf else min(hard, requested + FD_RESERVE)
        if target > soft:
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
                note = f"open-files limit raised from {soft} to {target}"
                soft = target
            except (ValueError, OSError):
                pass
    if soft == inf:
        return requested or None, note
    room = soft - FD_RESERVE if soft >= 2 * FD_RESERVE else soft // 2
    room = max(room, 1)
    if not requested:
        return room, note
    if requested > room:
        note = (f"{note}; " if note else "") + (
            f"max_connections {requested} lowered to {room}: the open-files limit is "
            f"{soft} (raise it with ulimit -n)")
        return room, note
    return requested, note


def guarded_protocol(*, header_timeout: float, body_timeout: float, body_min_rate: float,
                     max_connections: int | None) -> type[GuardedHttpToolsProtocol]:
    """A :class:`GuardedHttpToolsProtocol` subclass with these limits, for
    ``uvicorn.run(..., http=...)``.

    Parameters
    ----------
    header_timeout, body_timeout : float
        Seconds (see the module's docstring).
    body_min_rate : float
        Bytes per second.
    max_connections : int or None
        Open connections admitted (None: no cap).

    Returns
    -------
    type
    """
    return type("FlatserveHttpProtocol", (GuardedHttpToolsProtocol,), {
        "header_timeout": float(header_timeout), "body_timeout": float(body_timeout),
        "body_min_rate": float(body_min_rate), "max_connections": max_connections})
