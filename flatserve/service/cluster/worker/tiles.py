"""A chart's tiles in Ray actors of their own: :class:`RayTileHost`, a
:class:`~flatserve.tiles.TileHost` (docs/design.md, "Tiles of a chart across nodes").

The shard worker keeps the tiling's bookkeeping; each tile is a
:class:`~.tile_actor.TileActor`, called through a :class:`RemoteTile`. A lost tile
cannot be rebuilt alone (its halo came from the exchange): the host is marked
:attr:`RayTileHost.lost` and the shard's actor ends, for Ray to restart it.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Concatenate, ParamSpec, TypeVar

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
#: seconds a new tile's actor may take to be placed and to answer before the nodes
#: are asked whether any could ever hold it (none: the tile is lost; some: it is
#: waited for up to TILE_CALL_TIMEOUT_S)
TILE_START_TIMEOUT_S = 120.0
#: concurrent calls a tile's actor takes (queries read it at once; the group's
#: worker never lets a query meet an insert or an exchange)
TILE_CONCURRENCY = 16
#: the most tiles ``tiles="auto"`` gives a chart (as many as a field may ask for)
MAX_TILES = 64
#: seconds a status round waits for the tiles' answers (those later are left out)
STATUS_WAIT_S = 2.0

P = ParamSpec("P")
R = TypeVar("R")


def _read(method: Callable[Concatenate[Tile, P], R], timeout: float = TILE_CALL_TIMEOUT_S,
          moved: bool = False) -> Callable[Concatenate["RemoteTile", P], R]:
    """:class:`~flatserve.tiles.Tile`'s read ``method`` as one call of the tile's actor
    (:meth:`~.tile_actor.TileActor.run`), typed as the tile's; answered here by an
    empty tile while no actor is started. ``moved``: its answer is an exchange's
    bytes (:attr:`RayTileHost.exchanged`)."""

    def read(self: "RemoteTile", *args: P.args, **kw: P.kwargs) -> R:
        if self.actor is None:
            return method(Tile(self.ndim), *args, **kw)
        got = self._host.get(self.actor.run.remote(lambda t: method(t, *args, **kw)), timeout)
        if moved:
            self._host.moved(_nbytes(*got))
        return got

    read.__doc__ = method.__doc__
    return read


def _nbytes(*arrays) -> int:
    return sum(int(a.nbytes) for a in arrays if a is not None)


class RemoteTile:
    """A tile in a :class:`~.tile_actor.TileActor` with :class:`~flatserve.tiles.Tile`'s
    methods, each one call of the actor's (:class:`~..wire.TileCalls`). The actor
    starts on the first call that changes the tile. ``npoints``, ``generation`` and
    ``nchannels`` are those the last change returned (the tiled triangulation never
    runs a change beside another call)."""

    def __init__(self, host: "RayTileHost", ndim: int) -> None:
        self._host, self.ndim = host, ndim
        #: the :class:`~.tile_actor.TileActor`'s handle (None: not started)
        self.actor: Any = None
        self.npoints = self.generation = self.nchannels = 0

    def _changed(self, submit: Callable[[Any], Any]):
        """The result of a call that changes the tile (the actor started first); its
        state kept."""
        if self.actor is None:
            self.actor = self._host.spawn(self.ndim)
        res, (self.npoints, self.generation, self.nchannels) = self._host.get(submit(self.actor))
        return res

    def load(self, record) -> tuple[np.ndarray, np.ndarray]:
        """Load the tile from its record (sent to the actor): global ids, own flags."""
        return self._changed(lambda a: a.load.remote(bytes(record)))

    def load_part(self, key: str, source: str, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Load the tile from its snapshot part, read by the actor: global ids, own flags."""
        return self._changed(lambda a: a.load_part.remote(key, source, what))

    def insert(self, points, values, own: bool):
        if not own:  # an exchange round's points, sent to the tile that needs them
            self._host.moved(_nbytes(points, values))
        return self._changed(lambda a: a.insert.remote(points, values, own))

    def store_part(self, gid, known) -> tuple[str, int]:
        """Its record stored by the actor as a snapshot part unless ``known``: the key
        and the bytes stored."""
        return self._host.get(self.actor.store_part.remote(np.ascontiguousarray(gid, np.int64),
                                                           frozenset(known)))

    take = _read(Tile.take, moved=True)  # (points fetched from their owner)
    conflicts = _read(Tile.conflicts, moved=True)  # (which vertices each tile needs)
    answer = _read(Tile.answer, QUERY_CALL_TIMEOUT_S)
    locate = _read(Tile.locate, QUERY_CALL_TIMEOUT_S)
    within = _read(Tile.within, QUERY_CALL_TIMEOUT_S)
    own_flags = _read(Tile.own_flags)
    own_box = _read(Tile.own_box)
    own_rows = _read(Tile.own_rows)
    count_cells = _read(Tile.count_cells)
    star_foreign = _read(Tile.star_foreign)
    record = _read(Tile.record)


class RayTileHost(TileHost):
    """Tiles in :class:`~.tile_actor.TileActor` s on the Ray cluster this process is
    connected to, each reserving ``ray_shard_memory`` of a node's memory (``SPREAD``).

    Parameters
    ----------
    settings : Settings
        ``ray_shard_memory``, ``ray_tile_samples`` (``tiles="auto"``),
        ``shard_threads`` (each tile's threads; default its node's CPUs).
    parts : TileParts, optional
        The field's storage, where each tile stores and reads its own snapshot part
        (default: the parts pass through this process).
    start_timeout : float
        Seconds a new tile's actor may take to answer before the nodes are asked
        whether any could hold it (:meth:`spawn`).

    Attributes
    ----------
    lost : str or None
        Why a tile was lost (its actor died or stopped answering); None while all answer.
    stored : int
        Bytes of snapshot parts the tiles stored themselves.
    exchanged : int
        Bytes the exchange rounds moved between this process and the tiles' actors
        (scans' answers, points fetched and sent), beside the tiling's own counts
        (:attr:`flatserve.tiles.TiledTriangulation.stats`).
    """

    def __init__(self, settings, parts: TileParts | None = None, *,
                 start_timeout: float = TILE_START_TIMEOUT_S) -> None:
        self.ray = ray = ray_api()
        self.settings, self.parts = settings, parts
        self.start_timeout = float(start_timeout)
        self.stored = self.exchanged = 0
        self.lost: str | None = None
        self._remote = ray.remote(TileActor)
        #: resources each tile's actor asks for beside its memory (SQLite: this machine)
        self.pin = machine_pin(ray, settings)
        # every failure of Ray's (the actor dead or unreachable, its result lost, a
        # timeout) but a tile's own error (a task error) loses the tile
        self._lost_kinds = (ray.exceptions.RayError, ConnectionError)
        self._tiles: "weakref.WeakSet[RemoteTile]" = weakref.WeakSet()
        self._pool = ThreadPoolExecutor(MAX_TILES, thread_name_prefix="flatserve-tiles")
        self._lock = threading.Lock()

    def spawn(self, ndim: int):
        """A new, empty :class:`~.tile_actor.TileActor`, once it answers.

        Raises
        ------
        ShardUnavailableError
            Not answered within :attr:`start_timeout` while no live node (on SQLite,
            of this machine's address) has ``ray_shard_memory`` of Ray memory at
            all; or not within :data:`TILE_CALL_TIMEOUT_S`. The actor is killed and
            the host :attr:`lost`: the shard's actor restarts, to try again.
        """
        s = self.settings
        actor = self._remote.options(
            num_cpus=0, memory=s.ray_shard_memory, max_restarts=0, max_task_retries=0,
            max_concurrency=TILE_CONCURRENCY, scheduling_strategy="SPREAD",
            **({"resources": dict(self.pin)} if self.pin else {}),
        ).remote(ndim, s.shard_threads, self.parts)
        where = (" of this machine's address" if self.pin else "") + \
            f" with {s.ray_shard_memory} bytes of Ray memory"
        try:
            ref = actor.state.remote()
            ready, _ = self.ray.wait([ref], timeout=self.start_timeout)
            if not ready and self._fits():  # room somewhere: placed once freed, or slow
                log.warning("a tile's actor has not started within %g s (every node%s busy, "
                            "or a slow start): waiting", self.start_timeout, where)
                ready, _ = self.ray.wait([ref], timeout=TILE_CALL_TIMEOUT_S)
                why = (f"a tile's actor did not start within {TILE_CALL_TIMEOUT_S:g} s "
                       f"(every node{where} busy, or a slow start)")
            else:
                why = (f"a tile's actor was not placed within {self.start_timeout:g} s: no "
                       f"live node{where} (ray_shard_memory; ray start --memory)")
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
        memory in all (the cluster unreachable: False)."""
        try:
            return bool(nodes_with(self.ray, {"memory": self.settings.ray_shard_memory,
                                              **self.pin}))
        except Exception:
            return False

    def auto_tiles(self, nsamples: int) -> int:
        """``tiles="auto"`` on a cluster: one tile per ``ray_tile_samples`` samples (at
        most :data:`MAX_TILES`), whatever the cores of the group's node, so that every
        copy of the group cuts the same tiles.

        >>> from flatserve.service.settings import Settings
        >>> host = RayTileHost.__new__(RayTileHost)
        >>> host.settings = Settings(ray_tile_samples=100_000)
        >>> [host.auto_tiles(n) for n in (0, 100_000, 100_001, 10**9)]
        [1, 1, 2, 64]
        """
        per = self.settings.ray_tile_samples
        return max(1, min(MAX_TILES, -(-int(nsamples) // per)))

    def map(self, fn, items):
        """``fn`` of each item on this host's own threads, one per tile: they only wait
        for the tiles' actors, whatever this node's CPUs."""
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
        """The part read by the tile's new actor (with :attr:`parts`; else read here)."""
        if self.parts is None:
            return super().load_part(ndim, key, parts, source, what)
        tile = self.make(ndim)
        return (tile, *tile.load_part(key, source, what))

    def part(self, tile: RemoteTile, gid, known):
        """The tile's record stored by its actor (with :attr:`parts`: the key, and None
        for the bytes; else serialised there and returned here)."""
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
        except self.ray.exceptions.RayTaskError as exc:
            raise task_cause(exc) from None
        except self._lost_kinds as exc:
            self.lost = f"{type(exc).__name__}: {exc}"
            log.error("a tile of this shard was lost: %s", self.lost)
            raise ShardUnavailableError(
                "a tile of this shard was lost (its node died or it stopped answering); "
                "the shard restores itself from the snapshot and the log") from None

    def placement(self) -> list[dict]:
        """Each started tile's node, resident memory and points, as far as they answer
        within :data:`STATUS_WAIT_S` (never raises; a tile found dead is :attr:`lost`)."""
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
            except self.ray.exceptions.RayActorError as exc:
                self.lost = self.lost or f"{type(exc).__name__}: {exc}"
            except Exception:  # pragma: no cover - answered, then unreadable
                pass
        return out
