"""A tile of a chart in a Ray actor of its own: the one class of the cluster wing
that runs in a tile's process (:class:`TileActor`), and where it stores and reads
its snapshot parts (:class:`TileParts`).

The shard worker that owns the tile calls it through :class:`~.tiles.RemoteTile`
(:class:`~..wire.TileCalls`): the calls that change the tile by name, every read as
a function of the tile (:meth:`TileActor.run`).
"""
from __future__ import annotations

import contextlib
import os
from typing import Any, Callable

from ....parallel import set_shard_threads
from ....tiles import Tile, TileHost
from ..ray_env import node_cpus, node_id, rss_bytes


class TileParts:
    """Where the tiles of one field store and read their snapshot parts: the
    field's storage (:func:`~flatserve.service.log.backend.open_backend` of the
    settings, as a shard worker opens it), opened in the process that uses it
    for each part and closed again (a snapshot or a restore is rare; an open
    backend per tile would hold a database connection per tile for good);
    pickled as its settings and the field's id. Every node holding tiles must
    reach the database (or, SQLite, the data directory).

    Parameters
    ----------
    settings : Settings
    field_id : int
    """

    def __init__(self, settings, field_id: int) -> None:
        self.settings, self.field_id = settings, int(field_id)

    def _backend(self):
        from ...log.backend import open_backend

        return contextlib.closing(open_backend(self.settings, follower=True))

    def get(self, key: str) -> bytes:
        """The part's bytes (:meth:`~flatserve.service.log.backend.LogBackend.read_part`)."""
        with self._backend() as b:
            return b.read_part(self.field_id, key)

    def put(self, key: str, data: bytes) -> int:
        """Store the part (:meth:`~flatserve.service.log.backend.LogBackend.store_part`):
        bytes written, 0 if it was there."""
        with self._backend() as b:
            return b.store_part(self.field_id, key, data)


class TileActor:
    """A :class:`~flatserve.tiles.Tile` in a Ray actor (one process): empty at
    first, loaded by :meth:`load` or :meth:`load_part` (so that a damaged part is
    an error of the call, not the actor's death). A call that changes the tile
    (``insert``, the loads) returns its result with the tile's ``(npoints,
    generation, nchannels)``, so that the proxy (:class:`~.tiles.RemoteTile`)
    answers those without a call. With ``parts``, it stores and reads its own
    snapshot parts."""

    def __init__(self, ndim: int, threads: int | None, parts: TileParts | None = None) -> None:
        set_shard_threads(threads or node_cpus())
        self.ndim = ndim
        self.tile = Tile(ndim)
        self.parts = parts

    def state(self) -> tuple[int, int, int]:
        t = self.tile
        return t.npoints, t.generation, t.nchannels

    def load(self, record) -> tuple:
        """The tile from its record: its global ids and own flags, and its state."""
        self.tile, gid, own = TileHost().load(self.ndim, record)
        return (gid, own), self.state()

    def load_part(self, key: str, source: str, what: str) -> tuple:
        """:meth:`load` of the part ``key``, read from the field's storage here."""
        self.tile, gid, own = TileHost().load_part(self.ndim, key, self.parts.get,  # type: ignore[union-attr]
                                                    source, what)
        return (gid, own), self.state()

    def store_part(self, gid, known) -> tuple[str, int]:
        """Its record as a snapshot part, stored here unless ``known``: its key and
        the bytes stored."""
        key, blob = TileHost().part(self.tile, gid, known)
        return key, 0 if blob is None or self.parts is None else self.parts.put(key, blob)

    def insert(self, points, values, own: bool) -> tuple:
        return self.tile.insert(points, values, own), self.state()

    def run(self, read: Callable[[Tile], Any]) -> Any:
        """``read(tile)``: a call of the tile that changes nothing but its halo's
        bookkeeping (:class:`~.tiles.RemoteTile` sends each of
        :class:`~flatserve.tiles.Tile`'s reads as one)."""
        return read(self.tile)

    def node(self) -> dict:
        return {"node": node_id(), "pid": os.getpid(),
                "memory": rss_bytes(), "npoints": self.tile.npoints}
