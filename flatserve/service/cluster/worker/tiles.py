"""Tiles of a chart in Ray actors of their own: a :class:`~flatserve.tiles.TileHost`.

In cluster mode a one-chart field made with ``tiles`` is held by one shard group
(:mod:`..front.placement`) whose worker keeps only the tiling's bookkeeping (global
ids, owners, boxes); each tile (its triangulation, own points and halo) is a
:class:`~.tile_actor.TileActor` of its own, placed by Ray's ``SPREAD`` strategy over the
nodes with room (each reserves ``ray_shard_memory`` of its node's ``memory``).
So a chart's memory and its inserts spread over as many nodes as it has tiles:

* an insert goes to the tiles whose boxes hold its points, all at once (one
  call each, on the shard pool's threads); the exchange rounds of Tile & Merge
  (:meth:`~flatserve.tiles.TiledTriangulation.settle`) run between the actors,
  the group's worker routing what each tile sends (a round is a barrier: every
  tile scans, then every tile inserts what it received);
* the worker inserts each batch whole and settles it before it moves on
  (:meth:`~flatserve.Field.insert_prepared`), so a copy's tiles depend on the log
  alone: every copy of the group holds the same bits, and a query's
  ``min_position`` waits for the exchange of every batch up to it;
* a query is answered by the tile whose box holds it (handed on once if its
  cell has no own vertex there), each tile's rows in one call;
* a snapshot's part of a tile is that tile's record, serialised and stored by
  its actor (:class:`~.tile_actor.TileParts`: the field's storage, opened in the actor's
  process); a restore has each new actor read its tile's part itself, at once:
  a tile's bytes never pass through the group's process, which sends and
  receives only the tile's global ids and own flags (9 bytes a point);
* the actors belong to the group's worker: when it ends (restarted, deleted)
  they end with it. A tile that is lost (its node died) cannot be rebuilt alone,
  since its halo came from the exchange: the call raises
  :class:`~flatserve.service.status.ShardUnavailableError` (a query goes to the
  group's next copy), the host is marked :attr:`RayTileHost.lost`, and the
  group's actor ends itself so that Ray restarts it: it restores from the
  snapshot and the log, with new tile actors;
* a tile's actor that no live node could hold (none has ``ray_shard_memory`` of
  Ray ``memory``; on SQLite, none of this machine's address) is lost the same
  way once it has not started within :data:`TILE_START_TIMEOUT_S` (the
  restarted group tries again), instead of its calls waiting 30 minutes for
  room; where some node could hold it once its memory is free, it is waited for
  (:data:`TILE_CALL_TIMEOUT_S`).
"""
from __future__ import annotations

import contextlib
import logging
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

from ....tiles import Tile, TileHost
from ...status import ShardUnavailableError
from ..ray_env import machine_pin, nodes_with, ray_api, task_cause
from .tile_actor import TileActor, TileParts

log = logging.getLogger("flatserve.service.cluster")

#: seconds a tile's call may take before the tile counts as lost (an insert of a
#: slice, or the load of a tile of millions of points, takes seconds to minutes)
TILE_CALL_TIMEOUT_S = 1800.0
#: seconds a query's call on a tile may take (a query's rows in one tile)
QUERY_CALL_TIMEOUT_S = 300.0
#: seconds a new tile's actor may take to be placed and to answer (a node with room
#: found, its process started) before the nodes are asked whether any could ever hold
#: it: none, and the tile is lost; some, and it is waited for up to TILE_CALL_TIMEOUT_S
TILE_START_TIMEOUT_S = 120.0
#: concurrent calls a tile's actor takes (queries read it at once; the group's
#: worker never lets a query meet an insert or an exchange)
TILE_CONCURRENCY = 16
#: the most tiles ``tiles="auto"`` gives a chart (as many as a field may ask for)
MAX_TILES = 64
#: seconds a status round waits for the tiles' answers (those later are left out)
STATUS_WAIT_S = 2.0


def _nbytes(*arrays) -> int:
    return sum(int(a.nbytes) for a in arrays if a is not None)


class RemoteTile:
    """A tile in a :class:`~.tile_actor.TileActor`, with :class:`~flatserve.tiles.Tile`'s
    methods (made by :class:`RayTileHost`): each is one call of the actor's
    (:class:`~..wire.TileCalls`), a read of the tile as a function of it
    (:meth:`~.tile_actor.TileActor.run`). The actor is started on the first call that
    needs it (an empty tile that is never used costs nothing: its reads answer
    here). Its ``npoints``, ``generation`` and ``nchannels`` are those the last
    insert (or the load) returned: only those change them, and the tiled
    triangulation never runs one beside another call that reads them."""

    def __init__(self, host: "RayTileHost", ndim: int) -> None:
        self._host, self._ndim = host, ndim
        self._actor = None
        self.npoints = self.generation = self.nchannels = 0

    @property
    def actor(self):
        """The :class:`~.tile_actor.TileActor`'s handle (None: not started)."""
        return self._actor

    def _started(self):
        if self._actor is None:
            self._actor = self._host.spawn(self._ndim)
        return self._actor

    def _changed(self, ref):
        """The result of a call that changes the tile; its state kept."""
        res, (self.npoints, self.generation, self.nchannels) = self._host.get(ref)
        return res

    def _run(self, read: Callable[[Tile], Any], timeout: float = TILE_CALL_TIMEOUT_S):
        return self._host.get(self._started().run.remote(read), timeout)

    def load(self, record) -> tuple[np.ndarray, np.ndarray]:
        """Load the tile from its record (sent to the actor): its global ids and own
        flags."""
        return self._changed(self._started().load.remote(bytes(record)))

    def load_part(self, key: str, source: str, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Load the tile from its snapshot part, read by the actor: its global ids
        and own flags."""
        return self._changed(self._started().load_part.remote(key, source, what))

    def store_part(self, gid, known) -> tuple[str, int]:
        """Its record stored by the actor as a snapshot part (unless ``known``): the
        key and the bytes stored."""
        return self._host.get(self._started().store_part.remote(
            np.ascontiguousarray(gid, np.int64), frozenset(known)))

    def insert(self, points, values, own: bool):
        if not own:  # an exchange round's points, sent to the tile that needs them
            self._host.moved(_nbytes(points, values))
        return self._changed(self._started().insert.remote(points, values, own))

    def take(self, local):
        got = self._run(lambda t: t.take(local))
        self._host.moved(_nbytes(*got))  # points an exchange round fetches from their owner
        return got

    def conflicts(self, lo, hi, start, skip: int, **where):
        got = self._run(lambda t: t.conflicts(lo, hi, start, skip, **where))
        self._host.moved(_nbytes(*got))  # a scan's answer: which vertices each tile needs
        return got

    def answer(self, q, outside, order, threads, everywhere: bool):
        return self._run(lambda t: t.answer(q, outside, order, threads, everywhere),
                         QUERY_CALL_TIMEOUT_S)

    def locate(self, q, order, threads):
        return self._run(lambda t: t.locate(q, order, threads), QUERY_CALL_TIMEOUT_S)

    # -- reads an empty tile answers here (no actor started) --------------------------------
    def own_flags(self):
        return np.empty(0, np.uint8) if self._actor is None else self._run(Tile.own_flags)

    def own_box(self):
        return None if self._actor is None else self._run(Tile.own_box)

    def own_rows(self):
        if self._actor is None:
            return np.empty(0, np.uint8), np.empty((0, self._ndim)), None
        return self._run(Tile.own_rows)

    def within(self, q, radius, threads):
        if self._actor is None:
            return np.zeros(len(q), dtype=bool)
        return self._run(lambda t: t.within(q, radius, threads), QUERY_CALL_TIMEOUT_S)

    def count_cells(self) -> int:
        return 0 if self._actor is None else self._run(Tile.count_cells)

    def star_foreign(self) -> int:
        return 0 if self._actor is None else self._run(Tile.star_foreign)

    def record(self, gid):
        if self._actor is None:
            return Tile(self._ndim).record(gid)
        return self._run(lambda t: t.record(gid))


class RayTileHost(TileHost):
    """Tiles in :class:`~.tile_actor.TileActor` s on the Ray cluster this process is connected
    to (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``ray_shard_memory`` (each tile's reservation), ``ray_tile_samples``
        (``tiles="auto"``: samples per tile), ``shard_threads`` (each tile's
        threads; default its node's CPUs).
    parts : TileParts, optional
        The field's storage, where each tile stores and reads its own snapshot
        part. Default: the parts pass through this process (a library's
        tiled triangulation, the tests').
    start_timeout : float
        Seconds a new tile's actor may take to be placed and to answer before
        the nodes are asked whether any could hold it (:data:`TILE_START_TIMEOUT_S`,
        :meth:`spawn`).

    Attributes
    ----------
    lost : str or None
        Why a tile was lost (its actor died or stopped answering); None while all
        answer.
    stored : int
        Bytes of snapshot parts the tiles stored themselves.
    exchanged : int
        Bytes the exchange rounds moved between this process and the tiles' actors
        (each scan's answer, the points fetched from their owners and sent to the
        tiles that need them), beside the tiling's own counts
        (:attr:`flatserve.tiles.TiledTriangulation.stats`: rounds, points sent).
    """

    def __init__(self, settings, parts: TileParts | None = None, *,
                 start_timeout: float = TILE_START_TIMEOUT_S) -> None:
        ray = ray_api()
        rx = ray.exceptions
        self.ray = ray
        self.settings = settings
        self.parts = parts
        self.start_timeout = float(start_timeout)
        self.stored = 0
        self.exchanged = 0
        self._remote = ray.remote(TileActor)
        #: resources each tile's actor asks for beside its memory (SQLite: this machine)
        self.pin = machine_pin(ray, settings)
        # every failure of Ray's (the actor dead or unreachable, its result lost, a
        # timeout) but a tile's own error (a task error) loses the tile
        self._lost_kinds = (rx.RayError, ConnectionError)
        self._task_error = rx.RayTaskError
        self._dead = rx.RayActorError
        self.lost: str | None = None
        self._tiles: "weakref.WeakSet[RemoteTile]" = weakref.WeakSet()
        self._pool = ThreadPoolExecutor(MAX_TILES, thread_name_prefix="flatserve-tiles")
        self._lock = threading.Lock()

    def spawn(self, ndim: int):
        """A new, empty :class:`~.tile_actor.TileActor`, once it answers.

        Raises
        ------
        ShardUnavailableError
            It did not answer within :attr:`start_timeout` and no live node (on
            SQLite, of this machine's address) has ``ray_shard_memory`` of Ray
            memory at all, so it never will be placed; or it did not answer
            within :data:`TILE_CALL_TIMEOUT_S` (nodes with room busy, or its
            start slow). The actor is killed and the host :attr:`lost`, so
            that the group's actor ends and Ray restarts it, to try again.
        """
        s = self.settings
        actor = self._remote.options(
            num_cpus=0, memory=s.ray_shard_memory, max_restarts=0, max_task_retries=0,
            max_concurrency=TILE_CONCURRENCY, scheduling_strategy="SPREAD",
            **({"resources": dict(self.pin)} if self.pin else {}),
        ).remote(ndim, s.shard_threads, self.parts)
        where = " of this machine's address" if self.pin else ""
        try:
            ref = actor.state.remote()
            ready, _ = self.ray.wait([ref], timeout=self.start_timeout)
            if not ready and self._fits():  # room somewhere: placed once freed, or slow
                log.warning("a tile's actor has not started within %g s (every node%s with "
                            "%d bytes of Ray memory busy, or a slow start): waiting",
                            self.start_timeout, where, s.ray_shard_memory)
                ready, _ = self.ray.wait([ref], timeout=TILE_CALL_TIMEOUT_S)
                why = (f"a tile's actor did not start within {TILE_CALL_TIMEOUT_S:g} s "
                       f"(every node{where} with {s.ray_shard_memory} bytes of Ray memory "
                       "busy, or a slow start)")
            else:
                why = (f"a tile's actor was not placed within {self.start_timeout:g} s: no "
                       f"live node{where} has {s.ray_shard_memory} bytes of Ray memory "
                       "(ray_shard_memory; ray start --memory)")
        except self._lost_kinds as exc:  # the cluster itself failing
            ready, why = [], f"a tile's actor could not start: {type(exc).__name__}: {exc}"
        if ready:  # (an actor that failed to start fails its first call)
            return actor
        with contextlib.suppress(Exception):
            self.ray.kill(actor)
        self.lost = why
        log.error("a tile of this shard could not start: %s", why)
        raise ShardUnavailableError(why + "; the shard restarts to try again")

    def _fits(self) -> bool:
        """Some live node (with the pin's resources) has ``ray_shard_memory`` of Ray
        memory in all: a tile's actor can be placed there once it is free."""
        try:
            return bool(nodes_with(self.ray, {"memory": self.settings.ray_shard_memory,
                                              **self.pin}))
        except Exception:  # the cluster unreachable: nothing is known to fit
            return False

    def auto_tiles(self, nsamples: int) -> int:
        """``tiles="auto"`` on a cluster: one tile per ``ray_tile_samples`` samples (a
        tile's memory; at most :data:`MAX_TILES`), whatever the cores of the node
        the group runs on, so that every copy of the group cuts the same tiles.

        >>> from flatserve.service.settings import Settings
        >>> host = RayTileHost.__new__(RayTileHost)
        >>> host.settings = Settings(ray_tile_samples=100_000)
        >>> [host.auto_tiles(n) for n in (0, 100_000, 100_001, 10**9)]
        [1, 1, 2, 64]
        """
        per = self.settings.ray_tile_samples
        return max(1, min(MAX_TILES, -(-int(nsamples) // per)))

    def map(self, fn, items):
        """``fn`` of each item on threads of this host's own, one per tile: they only
        wait for the tiles' actors, whatever this node's CPUs (a shard pool of one
        thread would call the tiles one after another)."""
        return list(self._pool.map(fn, items))

    def make(self, ndim: int) -> RemoteTile:
        tile = RemoteTile(self, ndim)
        with self._lock:
            self._tiles.add(tile)
        return tile

    def load(self, ndim: int, record):
        tile = self.make(ndim)
        return (tile, *tile.load(record))

    def load_part(self, ndim: int, key: str, parts, source: str, what: str):
        """The part read by the tile's new actor (with :attr:`parts`; else read
        here and sent to it)."""
        if self.parts is None:
            return super().load_part(ndim, key, parts, source, what)
        tile = self.make(ndim)
        return (tile, *tile.load_part(key, source, what))

    def part(self, tile: RemoteTile, gid, known):
        """The tile's record stored by its actor (with :attr:`parts`: the key, and
        None for the bytes; else serialised there and returned here)."""
        if self.parts is None or tile.actor is None:  # (an empty tile: no actor started)
            return super().part(tile, gid, known)
        key, stored = tile.store_part(gid, known)
        with self._lock:
            self.stored += stored
        return key, None

    def moved(self, nbytes: int) -> None:
        """Count ``nbytes`` of an exchange round (:attr:`exchanged`)."""
        with self._lock:
            self.exchanged += nbytes

    def get(self, ref, timeout: float = TILE_CALL_TIMEOUT_S):
        """``ray.get``: a tile's own error raised as itself; a lost tile as
        :class:`~flatserve.service.status.ShardUnavailableError` (and :attr:`lost`)."""
        try:
            return self.ray.get(ref, timeout=timeout)
        except self._task_error as exc:
            raise task_cause(exc) from None
        except self._lost_kinds as exc:
            self.lost = f"{type(exc).__name__}: {exc}"
            log.error("a tile of this shard was lost: %s", self.lost)
            raise ShardUnavailableError(
                "a tile of this shard was lost (its node died or it stopped answering); "
                "the shard restores itself from the snapshot and the log") from None

    def placement(self) -> list[dict]:
        """Each started tile's node, resident memory and points, as far as they
        answer within :data:`STATUS_WAIT_S` (never raises; a tile found dead is
        :attr:`lost`)."""
        with self._lock:
            actors = [t.actor for t in list(self._tiles) if t.actor is not None]
        if not actors:
            return []
        try:
            refs = [a.node.remote() for a in actors]
            ready, _ = self.ray.wait(refs, num_returns=len(refs), timeout=STATUS_WAIT_S)
        except Exception:  # the cluster unreachable: the next round asks again
            return []
        out = []
        for ref in ready:
            try:
                out.append(self.ray.get(ref, timeout=0.1))
            except self._dead as exc:
                self.lost = self.lost or f"{type(exc).__name__}: {exc}"
            except Exception:  # pragma: no cover - answered, then unreadable
                pass
        return out
