"""How a front's call reaches a shard actor and its result comes back: Ray's.

:class:`RayTransport` submits a :class:`~..wire.ShardCall` to one copy's actor (a
query packed into one blob, :attr:`~..wire.ShardCall.packed`), waits for its result
on a thread or awaits it on the event loop, and says which errors lose the copy (the
actor dead, restarting or unreachable) and which are the worker's own. Which copy is
called, and what happens when it is lost, is :mod:`.failover`'s.
"""
from __future__ import annotations

import asyncio
from typing import Any

from ..ray_env import task_cause
from ..wire import ShardCall, pack, unpack


class _Submit:
    """A copy's actor as :class:`~..wire.ShardCalls` whose methods submit the call (a
    query packed, :meth:`~..worker.actor.ShardActor.query`) and return Ray's
    reference to its result."""

    def __init__(self, actor) -> None:
        self.actor = actor

    def query(self, work, kw, at_position, timeout):
        return self.actor.query.remote(pack((work, kw, at_position, timeout)))

    def parts(self, position, known, timeout):
        return self.actor.parts.remote(position, known, timeout)

    def applied(self, position, timeout):
        return self.actor.applied.remote(position, timeout)

    def status(self):
        return self.actor.status.remote()


class RayTransport:
    """Calls on shard actors through ``ray`` (the connected API).

    Attributes
    ----------
    lost : tuple of exception types
        The errors that lose a copy (dead, restarting, unreachable, timed out):
        the call goes to another copy. Any other is the worker's own error.
    """

    def __init__(self, ray) -> None:
        self.ray = ray
        rx = ray.exceptions
        self.lost = (rx.ActorUnavailableError, rx.GetTimeoutError, rx.RayActorError,
                     rx.RaySystemError, ConnectionError, asyncio.TimeoutError)
        self._task_error = rx.RayTaskError

    def submit(self, actor, call: ShardCall):
        """``call`` on ``actor``: Ray's reference to its result (:meth:`result` reads it)."""
        return call.run(_Submit(actor))

    def get(self, ref, timeout: float):
        """``ray.get`` with a worker's own error raised as itself."""
        try:
            return self.ray.get(ref, timeout=timeout)
        except self._task_error as exc:
            raise task_cause(exc) from None

    async def aget(self, ref, timeout: float):
        """:meth:`get` awaited on the event loop (a timeout: ``asyncio.TimeoutError``)."""
        try:
            return await asyncio.wait_for(asyncio.wrap_future(ref.future()), max(timeout, 0.0))
        except self._task_error as exc:
            raise task_cause(exc) from None

    @staticmethod
    def result(call: ShardCall, value) -> Any:
        """What ``call`` returned, from what :meth:`get` read."""
        return unpack(value) if call.packed else value

    def cancel(self, refs) -> None:
        """Calls still running, cancelled (those done, or a cluster gone: ignored)."""
        for r in list(refs):
            try:
                self.ray.cancel(r)
            except Exception:
                pass
