"""A shard worker as a Ray actor (:class:`ShardActor`): it holds a
:class:`~.shard.ShardWorker` whose tiles live in actors of their own
(:class:`~.tiles.RayTileHost`), answers :class:`..wire.ShardCalls` and adds where it
runs to its status. A lost tile ends the actor, for Ray to restart it.
"""
from __future__ import annotations

import logging
import os
import threading
import time

from ..ray_env import node_cpus, node_id
from .shard import ShardWorker
from ..wire import pack, unpack

log = logging.getLogger("flatserve.service.cluster")

#: seconds between two status rounds (a front's, :class:`~..front.health.StatusRound`;
#: an actor's look at where its tiles are)
STATUS_EVERY_S = 1.0


class ShardActor:
    """A :class:`~.shard.ShardWorker` as a Ray actor (one process)."""

    def __init__(self, settings, field_id: int, charts) -> None:
        from ....parallel import set_shard_threads
        from ... import logs
        from .tiles import RayTileHost, TileParts

        logs.configure(settings.log_level, settings.log_format)
        set_shard_threads(settings.shard_threads or node_cpus())
        self.tiles = RayTileHost(settings, TileParts(settings, field_id))
        self._tiles_at: list[dict] = []
        self.worker = ShardWorker(settings, field_id, charts, tile_host=self.tiles)
        threading.Thread(target=self._watch, name="flatserve-tiles-watch", daemon=True).start()

    def _watch(self) -> None:
        """Where the tiles are, each :data:`STATUS_EVERY_S` (for :meth:`status`, which
        never waits). A lost tile cannot be rebuilt alone (its halo came from the
        exchange): this actor then ends, and Ray restarts it to restore from the
        snapshot and the log."""
        while self.tiles.lost is None:
            self._tiles_at = self.tiles.placement()
            time.sleep(STATUS_EVERY_S)
        log.error("shard %s of field %d: %s; restarting to restore", self.worker.charts,
                  self.worker.field_id, self.tiles.lost)
        os._exit(1)

    def query(self, request: bytes) -> bytes:
        """:meth:`~.shard.ShardWorker.query`; arguments and answer packed
        (:attr:`..wire.ShardCall.packed`)."""
        return pack(self.worker.query(*unpack(request)))

    def parts(self, position, known, timeout):
        return self.worker.parts(position, known, timeout)

    def applied(self, position: int, timeout: float) -> dict:
        """:meth:`status` once the worker has applied the log up to ``position``
        (:meth:`~.shard.ShardWorker.applied`)."""
        got = self.worker.applied(position, timeout)
        return {**self.status(), "duplicates": got["duplicates"]}

    def status(self) -> dict:
        st = self.worker.status()
        if self.tiles.lost:  # (this actor ends, to be restarted: say why meanwhile)
            st["error"] = f"restarting: {self.tiles.lost}"
        return {**st, "node": node_id(), "tiles": self._tiles_at}


