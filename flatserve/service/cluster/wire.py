"""The calls between a cluster front and its actors, as methods of Protocols.

A front asks a shard group for what :class:`ShardCalls` declares
(:class:`~.worker.shard.ShardWorker` implements it); a call is made by this module's
functions (:func:`query`, :func:`parts`, :func:`applied`, :func:`status`), never by a
method's name, and a packed call's bytes are made and read here alone
(:func:`pack`, :func:`unpack`). A shard worker calls its tiles' actors through
:class:`TileCalls` (:class:`~.worker.tile_actor.TileActor`).
"""
from __future__ import annotations

import pickle
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

if TYPE_CHECKING:
    from ...tiles import Tile


class ShardCalls(Protocol):
    """What a front calls on a shard worker (:class:`~.worker.shard.ShardWorker`)."""

    def query(self, work: list, kw: dict, at_position: int, timeout: float) -> list:
        """Its charts' answers on the rows routed to them, once the log up to
        ``at_position`` is applied (:meth:`~.worker.shard.ShardWorker.query`)."""
        ...

    def parts(self, position: int, known, timeout: float) -> dict:
        """Its charts' snapshot parts at log ``position``, stored
        (:meth:`~.worker.shard.ShardWorker.parts`)."""
        ...

    def applied(self, position: int, timeout: float) -> dict:
        """Its status once the log up to ``position`` is applied
        (:meth:`~.worker.shard.ShardWorker.applied`)."""
        ...

    def status(self) -> dict:
        """What it holds and where it is in the log, now (:meth:`~.worker.shard.ShardWorker.status`)."""
        ...


@dataclass(frozen=True)
class ShardCall:
    """One call of :class:`ShardCalls` with its arguments: ``run(target)`` makes it on
    ``target`` (a worker, or the transport's stand-in that submits it).

    Attributes
    ----------
    run : callable
    packed : bool
        Arguments and result travel as one pickled ``bytes`` each way (a query:
        small and frequent; Ray's cost of a call grows with the objects it
        serialises).
    work : tuple
        A query's ``(chart, flats)`` pairs (empty otherwise), in its answers' order.
    """

    run: Callable[[Any], Any]
    packed: bool = False
    work: tuple = ()


def pack(value) -> bytes:
    """A packed call's arguments, or its result, as one blob (:attr:`ShardCall.packed`:
    the front packs a query's arguments, :class:`~.worker.actor.ShardActor` its answer)."""
    return pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)


def unpack(blob: bytes):
    """What :func:`pack` packed."""
    return pickle.loads(blob)


def query(work: list, kw: dict, at_position: int, timeout: float) -> ShardCall:
    """:meth:`ShardCalls.query` (packed)."""
    return ShardCall(lambda s: s.query(work, kw, at_position, timeout), packed=True,
                     work=tuple(work))


def parts(position: int, known, timeout: float) -> ShardCall:
    """:meth:`ShardCalls.parts`."""
    return ShardCall(lambda s: s.parts(position, known, timeout))


def applied(position: int, timeout: float) -> ShardCall:
    """:meth:`ShardCalls.applied`."""
    return ShardCall(lambda s: s.applied(position, timeout))


def status() -> ShardCall:
    """:meth:`ShardCalls.status`."""
    return ShardCall(lambda s: s.status())


class TileCalls(Protocol):
    """What a shard worker calls on a tile in an actor of its own: the calls that
    change the tile return its ``(npoints, generation, nchannels)`` beside their
    result; every read is one function of the tile (``run``), typed against
    :class:`flatserve.tiles.Tile`'s own methods (:class:`~.worker.tiles.RemoteTile`)."""

    def state(self) -> tuple[int, int, int]: ...

    def load(self, record) -> tuple: ...

    def load_part(self, key: str, source: str, what: str) -> tuple: ...

    def store_part(self, gid, known) -> tuple[str, int]: ...

    def insert(self, points, values, own: bool) -> tuple: ...

    def run(self, read: Callable[["Tile"], Any]) -> Any: ...

    def node(self) -> dict: ...
