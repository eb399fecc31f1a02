"""Failover, written once: one live copy of each shard group a request touches.

A request's calls (``{group: call}``, :mod:`..wire`) go to one copy of each group
(:class:`Copies`, in the order to try them); a copy that is lost (the transport's
:attr:`~.transport.RayTransport.lost`) or answers ``ShardUnavailableError``
(restoring, behind) is passed over for the group's next copy; a group with none left
fails the request. Any other error of a worker is the request's. :func:`call_async`
awaits the answers on the event loop; :func:`call` runs it on the calling thread.
"""
from __future__ import annotations

import asyncio
import time
from typing import Any, Protocol

from ...status import NotReadyError, ShardUnavailableError
from ..wire import ShardCall
from .transport import RayTransport


class Copies(Protocol):
    """A field's shard groups as failover sees them (:class:`~.placement.RayGroups`)."""

    transport: RayTransport

    def order(self, g: int) -> list[int]:
        """Group ``g``'s copies in the order to try them."""
        ...

    def actor(self, g: int, j: int):
        """Copy ``j`` of group ``g``."""
        ...

    def mark(self, g: int, j: int, alive: bool) -> None:
        """Copy ``j`` of group ``g`` answered (True) or was lost (False)."""
        ...

    def unavailable(self, g: int, last: str) -> ShardUnavailableError:
        """Group ``g`` has no copy left (``last``: why the last one failed)."""
        ...


class Fanout:
    """One request's calls to a field's groups, one copy of each (see the module doc)."""

    def __init__(self, copies: Copies, calls: dict[int, ShardCall], timeout: float) -> None:
        self.copies, self.calls = copies, calls
        self.transport = copies.transport
        self.deadline = time.monotonic() + timeout
        self.tried: dict[int, list[int]] = {g: [] for g in calls}
        self.last: dict[int, str] = {}

    def left(self) -> float:
        """Seconds left for the answers (at least 50 ms: a copy that answered counts)."""
        return max(0.05, self.deadline - time.monotonic())

    def submit(self, g: int) -> tuple[int, Any]:
        """Group ``g``'s call on its next copy: ``(copy, ref)``.

        Raises
        ------
        ShardUnavailableError
            Every copy of the group has been tried.
        """
        for j in self.copies.order(g):
            if j in self.tried[g]:
                continue
            self.tried[g].append(j)
            try:
                return j, self.transport.submit(self.copies.actor(g, j), self.calls[g])
            except Exception as exc:  # the cluster unreachable
                self.last[g] = f"{type(exc).__name__}: {exc}"
                self.copies.mark(g, j, False)
        raise self.copies.unavailable(g, self.last.get(g, "no answer"))

    def answered(self, g: int, j: int, result):
        """Copy ``j`` of group ``g`` answered ``result``: its value."""
        self.copies.mark(g, j, True)
        return self.transport.result(self.calls[g], result)

    def failed(self, g: int, j: int, exc: Exception) -> tuple[int, Any]:
        """Copy ``j`` of group ``g`` failed with ``exc``: the call on the next copy
        (:meth:`submit`), or ``exc`` raised when it is the worker's own error."""
        if isinstance(exc, ShardUnavailableError):  # restoring, behind, failed: another copy
            self.last[g] = str(exc)
        elif isinstance(exc, NotReadyError) or not isinstance(exc, self.transport.lost):
            raise exc
        else:
            self.last[g] = f"{type(exc).__name__}: {exc}"
            self.copies.mark(g, j, False)
        return self.submit(g)


def call(copies: Copies, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
    """:func:`call_async` waited for on this thread (never the event loop's)."""
    return asyncio.run(call_async(copies, calls, timeout))


async def call_async(copies: Copies, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
    """``{group: call}`` on one live copy of each group: submitted at once, their
    results awaited; nothing blocks the loop but the submission (the transport's
    serialisation of the arguments: small calls only on a server's event loop)."""
    fan = Fanout(copies, calls, timeout)
    first = {g: fan.submit(g) for g in calls}
    live: dict[int, Any] = {}

    async def one(g: int):
        j, ref = first[g]
        while True:
            live[g] = ref
            try:
                return g, fan.answered(g, j, await fan.transport.aget(ref, fan.left()))
            except Exception as exc:
                fan.transport.cancel([ref])  # (a copy that timed out may still be at it)
                j, ref = fan.failed(g, j, exc)

    tasks = [asyncio.ensure_future(one(g)) for g in calls]
    try:
        return dict(await asyncio.gather(*tasks))
    except BaseException:
        for t in tasks:
            t.cancel()
        fan.transport.cancel(live.values())
        raise
