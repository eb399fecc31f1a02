"""A tile of a chart in a Ray actor of its own (:class:`TileActor`, called through
:class:`~.tiles.RemoteTile`), and where it stores and reads its snapshot parts
(:class:`TileParts`).
"""
from __future__ import annotations

import contextlib
import os
from typing import Any, Callable

from ....parallel import set_shard_threads
from ....tiles import Tile, TileHost
from ..ray_env import node_cpus, node_id, rss_bytes


class TileParts:
    """The field's storage (:func:`~flatserve.service.log.backend.open_backend`, as a
    shard worker opens it), opened in the tile's process for each part and closed
    again (an open backend per tile would hold a database connection per tile for
    good); pickled as the settings and the field's id. Every node holding tiles must
    reach the database (or, SQLite, the data directory)."""

    def __init__(self, settings, field_id: int) -> None:
        self.settings, self.field_id = settings, int(field_id)

    def _backend(self):
        from ...log.backend import open_backend

        return contextlib.closing(open_backend(self.settings, follower=True))

    def get(self, key: str) -> bytes:
        """The part's bytes."""
        with self._backend() as b:
            return b.read_part(self.field_id, key)

    def put(self, key: str, data: bytes) -> int:
        """Store the part: bytes written, 0 if it was there."""
        with self._backend() as b:
            return b.store_part(self.field_id, key, data)


class TileActor:
    """A :class:`~flatserve.tiles.Tile` in a Ray actor (:class:`~..wire.TileCalls`):
    empty at first, loaded by a call (a damaged part is an error of the call, not
    the actor's death). A call that changes the tile returns its result with the
    tile's ``(npoints, generation, nchannels)``; every read is one function of the
    tile (:meth:`run`)."""

    def __init__(self, ndim: int, threads: int | None, parts: TileParts | None = None) -> None:
        set_shard_threads(threads or node_cpus())
        self.ndim, self.tile, self.parts = ndim, Tile(ndim), parts

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
        """``read(tile)``: a read of the tile (it changes nothing but its halo's
        bookkeeping)."""
        return read(self.tile)

    def node(self) -> dict:
        return {"node": node_id(), "pid": os.getpid(),
                "memory": rss_bytes(), "npoints": self.tile.npoints}
