"""Where a field's shard groups live: :class:`RayCluster` (a front's connection) and
:class:`RayGroups` (one field's groups, a :class:`~.remote.ShardGroups`).

A field's charts are dealt round-robin into ``ray_shards`` groups (:func:`deal`);
each group has :func:`placed_copies` detached actors (``max_restarts=-1``) named
``field-<log>-<id>-g<group>-c<copy>`` (:func:`log_tag`), on different nodes (a
``STRICT_SPREAD`` placement group), each reserving ``ray_shard_memory`` of its
node's ``memory``. Calls go through :mod:`.transport` with :mod:`.failover`; what is
known of each copy is :mod:`.health`'s (docs/design.md, "Shard groups").
"""
from __future__ import annotations

import hashlib
import logging
import threading
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ...status import ShardUnavailableError
from .. import wire
from ..ray_env import connect, machine_pin, nodes_with, one_machine, ray_api
from ..wire import ShardCall
from ..worker.actor import ShardActor
from . import failover
from .health import GroupHealth, StatusRound
from .transport import RayTransport

log = logging.getLogger("flatserve.service.cluster")

#: concurrent calls an actor takes (queries beside its log follower and snapshots)
ACTOR_CONCURRENCY = 16


def deal(ncharts: int, ngroups: int) -> list[tuple[int, ...]]:
    """Charts dealt round-robin into at most ``ngroups`` groups (neighbouring charts,
    which share their overlap's samples, go to different groups: the load is even).

    >>> deal(5, 2)
    [(0, 2, 4), (1, 3)]
    """
    n = max(1, min(ngroups, ncharts))
    return [tuple(range(g, ncharts, n)) for g in range(n)]


def log_tag(settings) -> str:
    """Eight hex digits naming the log a front follows (PostgreSQL's host, port and
    database, or the SQLite data directory), in its actors' names: two deployments
    sharing a Ray namespace never take each other's actors for their own."""
    url = settings.database_url
    if url:
        u = urlsplit(url)
        where = f"pg:{u.hostname}:{u.port}:{u.path}"
    else:
        where = f"sqlite:{Path(settings.data_dir).resolve()}"
    return hashlib.sha256(where.encode()).hexdigest()[:8]


class RayCluster:
    """A front's connection to the Ray cluster at ``settings.ray`` holding the shards
    (``ray_namespace``, ``ray_shards``, ``ray_shard_memory``; ``database_url`` unset:
    SQLite in ``data_dir``, every node on this machine). ShardUnavailableError: the
    cluster cannot be reached, or, on SQLite, has a node on another machine."""

    def __init__(self, settings) -> None:
        connect(settings)
        ray = ray_api()

        self.ray = ray
        if settings.database_url is None:  # SQLite: the workers read this data directory
            settings = settings.model_copy(update={"data_dir": Path(settings.data_dir).resolve()})
            one_machine(ray, settings)
        self.settings = settings
        #: resources each actor asks for beside its memory (SQLite: this machine's nodes)
        self.pin = machine_pin(ray, settings)
        self.log_tag = log_tag(settings)
        self.address = settings.ray
        self.transport = RayTransport(ray)
        self.actor_class = ray.remote(ShardActor)
        self._fields: dict[int, RayGroups] = {}
        self._lock = threading.Lock()
        self.status_round = StatusRound(ray, self.address, self._refreshers)
        log.info("cluster mode: shards on the Ray cluster at %s (namespace %r)", self.address,
                 settings.ray_namespace)

    def no_room(self) -> str | None:
        """Why a shard that runs nowhere cannot be placed now, or None
        (:meth:`~.health.StatusRound.no_room`)."""
        need = {"memory": self.settings.ray_shard_memory, **self.pin}
        return self.status_round.no_room(need, self.settings.ray_shard_memory)

    def _refreshers(self) -> list:
        with self._lock:
            return [g.refresh for g in self._fields.values()]

    # -- a field's groups ----------------------------------------------------------------
    def groups(self, field_id: int, ncharts: int, copies: int,
               name: str | None = None) -> "RayGroups":
        """The field's groups of actors, made unless they exist (any front may ask)."""
        with self._lock:
            g = self._fields.get(field_id)
            if g is None:
                g = self._fields[field_id] = RayGroups(self, field_id, ncharts, copies, name)
            return g

    def drop(self, field_id: int) -> None:
        """The field was deleted: its actors and placement groups go."""
        with self._lock:
            g = self._fields.pop(field_id, None)
        if g is not None:
            g.kill()

    def close(self) -> None:
        self.status_round.close()


def placed_copies(asked: int, room: int | None) -> int:
    """The copies of a shard group a front places: ``asked`` as far as the live nodes
    with room for one (``room``; None: unknown) hold them, one a node, at least 1.

    >>> placed_copies(3, 2), placed_copies(8, 3), placed_copies(0, 3), placed_copies(2, 0)
    (2, 3, 1, 1)
    """
    n = max(1, int(asked))
    return n if room is None else max(1, min(n, int(room)))


class RayGroups:
    """One field's shard groups on the cluster (a :class:`~.remote.ShardGroups`): a
    group's copies are counted when its placement group is first made (every front
    takes the count from it); more are placed as nodes join (:meth:`grow`)."""

    def __init__(self, cluster: RayCluster, field_id: int, ncharts: int, copies: int,
                 name: str | None = None) -> None:
        self.cluster = cluster
        self.field_id = field_id
        #: how errors name the field: its name (the actors are named by its id)
        self.label = f"field {name!r}" if name is not None else f"field {field_id}"
        #: the copies the field's definition asks for (at least 1)
        self.copies = max(1, int(copies))
        s = cluster.settings
        self.charts = deal(ncharts, s.ray_shards)
        try:
            room: int | None = len(nodes_with(cluster.ray, {"memory": s.ray_shard_memory,
                                                            **cluster.pin}))
        except Exception:  # pragma: no cover - the cluster unreachable: as asked
            room = None
        placed = placed_copies(copies, room)
        if int(copies) < 1:
            log.error("%s: its definition asks for %r copies of each shard; placing 1",
                      self.label, copies)
        elif placed < self.copies:
            log.warning("%s asks for %d copies of each shard but %d live node(s) have "
                        "room for one (ray_shard_memory %d bytes): %d placed (describe's "
                        "shard_groups say how many are live)", self.label, self.copies, room,
                        s.ray_shard_memory, placed)
        self.actors = [self._copies(g, placed) for g in range(len(self.charts))]
        self.transport = cluster.transport
        #: what is known of each copy, and each group's newest report
        self.health = GroupHealth([len(a) for a in self.actors])
        self._growing = threading.Lock()

    def _name(self, g: int, j: int | None = None) -> str:
        base = f"field-{self.cluster.log_tag}-{self.field_id}-g{g}"
        return base if j is None else f"{base}-c{j}"

    def _copies(self, g: int, placed: int) -> list:
        """Group ``g``'s actors: as many as its placement group (made here with
        ``placed`` bundles, or by any front earlier) has bundles."""
        if self.copies == 1:
            return [self._actor(g, 0, None)]
        pg = self._placement(g, placed)
        try:
            n = max(1, int(pg.bundle_count))
        except Exception:  # pragma: no cover - the cluster unreachable: as made here
            n = placed
        return [self._actor(g, j, pg) for j in range(n)]

    def _placement(self, g: int, n: int):
        """The group's placement group (``n`` bundles if made here): its copies on
        different nodes."""
        util = self.cluster.ray.util
        get_placement_group, placement_group = util.get_placement_group, util.placement_group
        name = self._name(g)
        try:
            return get_placement_group(name)
        except ValueError:
            pass
        mem = self.cluster.settings.ray_shard_memory
        try:
            return placement_group([{"memory": mem, **self.cluster.pin}] * n,
                                   strategy="STRICT_SPREAD",
                                   name=name, lifetime="detached")
        except Exception:  # made by another front meanwhile
            return get_placement_group(name)

    def _actor(self, g: int, j: int, pg, node: str | None = None):
        """Copy ``j`` of group ``g`` (made unless it exists): in bundle ``j`` of the
        placement group ``pg``, else on ``node`` (preferred: elsewhere when it is gone
        or full), else spread."""
        s, ways = self.cluster.settings, self.cluster.ray.util.scheduling_strategies
        strategy: Any = "SPREAD"
        if pg is not None:
            strategy = ways.PlacementGroupSchedulingStrategy(pg, placement_group_bundle_index=j)
        elif node is not None:
            strategy = ways.NodeAffinitySchedulingStrategy(node, soft=True)
        opts: dict[str, Any] = dict(
            name=self._name(g, j), namespace=s.ray_namespace, lifetime="detached",
            get_if_exists=True, max_restarts=-1, max_task_retries=0, scheduling_strategy=strategy,
            max_concurrency=ACTOR_CONCURRENCY, num_cpus=0, memory=s.ray_shard_memory)
        if self.cluster.pin:  # (with copies, from its bundle, which holds as much)
            opts["resources"] = dict(self.cluster.pin)
        return self.cluster.actor_class.options(**opts).remote(s, self.field_id, self.charts[g])

    def grow(self) -> None:
        """Place a copy a group lacks on a live node with room that holds none of its
        copies (as their status reports named them), once one has joined: one copy a
        group a round, named as the next copy (any front finds it; made once)."""
        short = [g for g, a in enumerate(self.actors) if len(a) < self.copies]
        if not short or not self._growing.acquire(blocking=False):  # (one round at a time)
            return
        try:
            self._grow(short)
        finally:
            self._growing.release()

    def _grow(self, short: list[int]) -> None:
        ray, s = self.cluster.ray, self.cluster.settings
        try:
            room = [n["NodeID"] for n in nodes_with(ray, {"memory": s.ray_shard_memory,
                                                          **self.cluster.pin})]
        except Exception:  # the cluster unreachable: the next round tries again
            return
        for g in short:
            held = self.health.nodes[g]
            if None in held:  # a copy's node not known yet
                continue
            free = [n for n in room if n not in held]
            if not free:
                continue
            j = len(self.actors[g])
            log.info("%s: shard group %d gets its copy %d on a node that joined (asked: %d)",
                     self.label, g, j + 1, self.copies)
            actor = self._actor(g, j, None, free[0])
            self.health.add_copy(g)  # (the lists grow whole: readers see one or the other)
            self.actors[g] = [*self.actors[g], actor]

    def status(self) -> list[dict | None]:
        return list(self.health.reports)

    def placement(self) -> list[dict]:
        """Per group: its charts, the copies asked for and live, and the most advanced
        copy's last report (log position, samples, memory, node, restore source)."""
        out = []
        h = self.health
        why = self.cluster.no_room() if any(h.idle(g) for g in range(len(self.charts))) else None
        for g, charts in enumerate(self.charts):
            st = h.reports[g] or {}
            out.append({"charts": list(charts), "copies": self.copies, "live": h.live(g),
                        "unplaced": why if h.idle(g) else None,
                        "position": st.get("through"),
                        "samples": st.get("nsamples"), "memory": st.get("rss"),
                        "node": st.get("node"), "restored_from": st.get("restored_from"),
                        "tiles": st.get("tiles") or None})
        return out

    def refresh(self, timeout: float = 2.0) -> None:
        """Ask every actor for its status (one round, at most ``timeout`` s), then place
        the copies a group lacks where nodes have joined (:meth:`grow`)."""
        self.health.refresh(self.transport, self.actors, timeout)
        self.grow()

    def applied(self, position: int, timeout: float) -> list[dict]:
        """Per group, a copy's status once it has applied the log up to ``position``
        (ShardUnavailableError: none there within ``timeout``)."""
        got = self.call({g: wire.applied(position, timeout) for g in range(len(self.charts))},
                        timeout + 5.0)
        for g, st in got.items():
            self.health.note(g, st)
        return [got[g] for g in range(len(self.charts))]

    def call(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """``{group: call}`` (:mod:`..wire`) on one live copy of each group, waited for
        on this thread (:func:`.failover.call`)."""
        return failover.call(self, calls, timeout)

    async def call_async(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """:meth:`call` awaited on the event loop (:func:`.failover.call_async`)."""
        return await failover.call_async(self, calls, timeout)

    # -- what failover asks (:class:`.failover.Copies`) --------------------------------------
    def order(self, g: int) -> list[int]:
        n = len(self.actors[g])  # (a copy being added is counted once it is made)
        return [j for j in self.health.order(g) if j < n]

    def actor(self, g: int, j: int):
        return self.actors[g][j]

    def mark(self, g: int, j: int, alive: bool) -> None:
        self.health.mark(g, j, alive)

    def unavailable(self, g: int, last: str) -> ShardUnavailableError:
        head = (f"{self.label}: shard group {g} (charts {list(self.charts[g])}) has no "
                f"live copy of {len(self.actors[g])} now ({last})")
        why = self.cluster.no_room() if self.health.idle(g) else None
        if why is not None:
            return ShardUnavailableError(f"{head}; it cannot be placed: {why}")
        return ShardUnavailableError(f"{head}; its actors are restarted and restore themselves: "
                                     "retry shortly")

    def kill(self) -> None:
        ray = self.cluster.ray
        for copies in self.actors:
            for a in copies:
                try:
                    ray.kill(a, no_restart=True)
                except Exception:
                    pass
        if self.copies > 1:  # (a placement group per group: _copies)
            util = ray.util
            for g in range(len(self.charts)):
                try:
                    util.remove_placement_group(util.get_placement_group(self._name(g)))
                except Exception:
                    pass
