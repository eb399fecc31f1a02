"""Shard workers as Ray actors, the front's side: placement, copies, calls with failover, status.

Ray's own calls for connecting and for the nodes are :mod:`.ray_env`'s (the
``cluster`` extra). :class:`RayCluster` is a front's connection to the
cluster; :meth:`RayCluster.groups` gives a field's :class:`RayGroups` (a
:class:`~.remote.ShardGroups`):

* a field's charts are dealt round-robin into ``ray_shards`` groups (a
  one-chart field: one group); each group has ``copies`` actors (the field's
  spec) as far as the live nodes with room hold them, one a node
  (:func:`placed_copies`: never more, never fewer than 1), named
  ``field-<log>-<id>-g<group>-c<copy>`` in ``ray_namespace``
  (``<log>``: :func:`log_tag`, the log's location), detached
  (they outlive the front that made them: any front finds them by name) and
  restarted by Ray wherever there is room when their node dies
  (``max_restarts=-1``); a restarted actor restores itself
  (:class:`~.actor.ShardActor`, holding a :class:`~.shard.ShardWorker`: the one
  class that runs in the actor's process);
* each actor reserves ``ray_shard_memory`` bytes of its node's ``memory``
  resource, so a node holds shards up to its budget, and inserts and answers
  on as many threads as its node has CPUs (``shard_threads`` if set); the copies of a group are
  placed on different nodes (a ``STRICT_SPREAD`` placement group), the groups
  of a field spread over the nodes (``SPREAD``);
* a call goes to one copy of each group; a copy that is dead, restarting,
  restoring or behind is passed over for the next; a group with no copy
  left is :class:`~flatserve.service.status.ShardUnavailableError` (503);
  :meth:`RayGroups.call` waits on the calling thread,
  :meth:`RayGroups.call_async` on the event loop (Ray's results are
  awaitable): the same failover (:class:`_Fanout`);
* a query travels as one pickled ``bytes`` each way
  (:attr:`.wire.ShardCall.packed`): Ray's cost of a small call grows with the
  objects it serialises (measured on 2 cores: four arguments and a list of
  results 1.8 ms a call, one blob each way 1.3 ms, a call of nothing 1.2 ms);
* a thread asks every actor for its status each second
  (:meth:`RayGroups.status` never waits for it; a copy not heard from yet is
  not counted live); :meth:`RayGroups.refresh` asks at once (describe), and
  :meth:`RayGroups.applied` asks once a log position is applied (an upload
  with ``wait=true``).
"""
from __future__ import annotations

import asyncio
import hashlib
import logging
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ...status import NotReadyError, ShardUnavailableError
from ..worker.actor import STATUS_EVERY_S, ShardActor
from ..ray_env import (connect, machine_pin, nodes_with, one_machine, probe_address, ray_api,
                      task_cause)
from .. import wire
from ..wire import ShardCall, pack, unpack

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
    database; or the SQLite data directory's absolute path), in its actors' names:
    two deployments sharing one Ray cluster and namespace never take each other's
    actors for their own fields of the same id (detached actors outlive their
    front, and fronts find them by name). Every front of a deployment names its
    database alike (one set of actors per spelling of the host)."""
    url = settings.database_url
    if url:
        u = urlsplit(url)
        where = f"pg:{u.hostname}:{u.port}:{u.path}"
    else:
        where = f"sqlite:{Path(settings.data_dir).resolve()}"
    return hashlib.sha256(where.encode()).hexdigest()[:8]


class RayCluster:
    """A front's connection to the Ray cluster holding the shards (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``ray`` (the address), ``ray_namespace``, ``ray_shards``,
        ``ray_shard_memory``, and what the workers need (``database_url``; unset:
        SQLite in ``data_dir``, for a cluster whose nodes are all on this machine).

    Raises
    ------
    ShardUnavailableError
        The cluster cannot be reached (the message names the address), or, on
        SQLite, has a node on another machine.
    """

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
        rx = ray.exceptions
        self._lost = (rx.ActorUnavailableError, rx.GetTimeoutError, rx.RayActorError,
                      rx.RaySystemError, ConnectionError, asyncio.TimeoutError)
        self._task_error = rx.RayTaskError
        self._remote = ray.remote(ShardActor)
        self._fields: dict[int, RayGroups] = {}
        #: the cluster's free resources at the last status round (None: not read, or
        #: the cluster unreachable then): :meth:`no_room`
        self._free: dict | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll, name="flatserve-shard-status",
                                        daemon=True)
        self._poller.start()
        log.info("cluster mode: shards on the Ray cluster at %s (namespace %r)", self.address,
                 settings.ray_namespace)

    def no_room(self) -> str | None:
        """Why a shard that runs nowhere cannot be placed now, with what would fix it, or
        None when the live nodes have room for one (it is starting, or its node is
        being replaced). A shard reserves ``ray_shard_memory`` bytes of a node's
        ``memory`` resource (:meth:`RayGroups._actor`); the nodes' free resources are
        the cluster's (``ray.available_resources``) as the status round last read them:
        no call to the cluster here (a query's 503 may be made on the event loop, and a
        cluster that went away would hold it); none known (the cluster unreachable): None."""
        need = {"memory": self.settings.ray_shard_memory, **self.pin}
        free = self._free
        if free is None or all(free.get(r, 0) >= v for r, v in need.items()):
            return None
        return (f"no live node has room for it: a shard reserves ray_shard_memory "
                f"{need['memory']:,} bytes of a node's memory resource and the live nodes "
                f"have {int(free.get('memory', 0)):,} bytes free in all; add a node, start the "
                "nodes with a larger --memory, lower FLATSERVE_RAY_SHARD_MEMORY or "
                "FLATSERVE_RAY_SHARDS, or delete a field")

    # -- a field's groups ----------------------------------------------------------------
    def groups(self, field_id: int, ncharts: int, copies: int) -> "RayGroups":
        """The field's groups of actors, made unless they exist (any front may ask)."""
        with self._lock:
            g = self._fields.get(field_id)
            if g is None:
                g = self._fields[field_id] = RayGroups(self, field_id, ncharts, copies)
            return g

    def drop(self, field_id: int) -> None:
        """The field was deleted: its actors and placement groups go."""
        with self._lock:
            g = self._fields.pop(field_id, None)
        if g is not None:
            g.kill()

    def close(self) -> None:
        self._stop.set()
        self._poller.join(timeout=5)

    # -- calls ----------------------------------------------------------------------------
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

    def _poll(self) -> None:
        lost = False
        while not self._stop.wait(STATUS_EVERY_S):
            with self._lock:
                fields = list(self._fields.values())
            for g in fields:
                try:
                    g.refresh()
                except Exception:  # the cluster unreachable: the next round tries again
                    log.debug("status round failed", exc_info=True)
            try:
                probe_address(self.address, timeout=2.0)
                try:
                    self._free = dict(self.ray.available_resources())
                except Exception:  # pragma: no cover - lost between the probe and the call
                    self._free = None
                if lost:
                    log.warning("the Ray cluster at %s answers again", self.address)
                lost = False
            except ShardUnavailableError as exc:
                self._free = None
                if not lost:
                    log.error("%s: queries answer 503 meanwhile; Ray ends this front after its "
                              "reconnect timeout (RAY_gcs_rpc_server_reconnect_timeout_s, 60 s by "
                              "default), for its supervisor to start it again once the cluster "
                              "is back", exc)
                lost = True


def placed_copies(asked: int, room: int | None) -> int:
    """How many copies of a shard group a front places: the field's ``copies``
    (``asked``) as far as the cluster's live nodes with room for one (``room``;
    None: unknown, as asked) hold them, one a node, and never fewer than 1 (a
    stored definition asking 0 or fewer still gets its one copy).

    >>> placed_copies(3, 2), placed_copies(8, 3), placed_copies(0, 3), placed_copies(2, 0)
    (2, 3, 1, 1)
    """
    n = max(1, int(asked))
    return n if room is None else max(1, min(n, int(room)))


class RayGroups:
    """One field's shard groups on the cluster (a :class:`~.remote.ShardGroups`).

    A group has :func:`placed_copies` copies: the field's ``copies`` as far as the
    live nodes with room hold them when its placement group is first made (every
    front takes that count from the placement group then: the copies are
    ``c0``-``c<n-1>`` everywhere). Describe's ``copies`` is the field's ``copies``
    (what it asks) and ``live`` the copies that answered a status round or a call:
    0 until one has (a copy is not counted live before it is heard from).
    """

    def __init__(self, cluster: RayCluster, field_id: int, ncharts: int, copies: int) -> None:
        self.cluster = cluster
        self.field_id = field_id
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
            log.error("field %d: its definition asks for %r copies of each shard; placing 1",
                      field_id, copies)
        elif placed < self.copies:
            log.warning("field %d asks for %d copies of each shard but %d live node(s) have "
                        "room for one (ray_shard_memory %d bytes): %d placed (describe's "
                        "shard_groups say how many are live)", field_id, self.copies, room,
                        s.ray_shard_memory, placed)
        self._status: list[dict | None] = [None] * len(self.charts)
        self._next = [0] * len(self.charts)
        self.actors = [self._copies(g, placed) for g in range(len(self.charts))]
        #: per group, per copy: True (its last status or call answered, ready), False
        #: (its last call failed, or it was not ready), None (not heard from yet, or
        #: silent in the last status round: unknown, not counted live)
        self._alive: list[list[bool | None]] = [[None] * len(a) for a in self.actors]

    def _name(self, g: int, j: int | None = None) -> str:
        base = f"field-{self.cluster.log_tag}-{self.field_id}-g{g}"
        return base if j is None else f"{base}-c{j}"

    def _copies(self, g: int, placed: int) -> list:
        """Group ``g``'s actors: ``placed`` of them, or as many as its placement group
        (made by any front, earlier) has bundles; a field asking for several copies
        has one, even when one copy is placed now."""
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

    def _actor(self, g: int, j: int, pg):
        s = self.cluster.settings
        opts: dict[str, Any] = dict(
            name=self._name(g, j), namespace=s.ray_namespace, lifetime="detached",
            get_if_exists=True, max_restarts=-1, max_task_retries=0,
            max_concurrency=ACTOR_CONCURRENCY, num_cpus=0, memory=s.ray_shard_memory)
        if self.cluster.pin:  # (with copies, from its bundle, which holds as much)
            opts["resources"] = dict(self.cluster.pin)
        if pg is not None:
            strategies = self.cluster.ray.util.scheduling_strategies
            opts["scheduling_strategy"] = strategies.PlacementGroupSchedulingStrategy(
                pg, placement_group_bundle_index=j)
        else:
            opts["scheduling_strategy"] = "SPREAD"
        return self.cluster._remote.options(**opts).remote(s, self.field_id, self.charts[g])

    def status(self) -> list[dict | None]:
        return list(self._status)

    def placement(self) -> list[dict]:
        """Per group: its charts, the copies the field asks for, the copies live (heard
        from, ready: a copy not heard from yet is not counted), and the most advanced
        copy's log position, samples, memory and restore source as it last reported
        them (none yet: None)."""
        out = []
        idle = [g for g in range(len(self.charts)) if not any(a is True for a in self._alive[g])]
        why = self.cluster.no_room() if idle else None
        for g, charts in enumerate(self.charts):
            st = self._status[g] or {}
            out.append({"charts": list(charts), "copies": self.copies,
                        "live": sum(a is True for a in self._alive[g]),
                        "unplaced": why if g in idle else None,
                        "position": st.get("through"),
                        "samples": st.get("nsamples"), "memory": st.get("rss"),
                        "node": st.get("node"), "restored_from": st.get("restored_from"),
                        "tiles": st.get("tiles") or None})
        return out

    def _note(self, g: int, st: dict) -> None:
        """A copy of group ``g`` reported ``st``: the group's report unless an earlier
        one was further on in the log."""
        old = self._status[g]
        if old is None or st["through"] >= old["through"]:
            self._status[g] = st

    def refresh(self, timeout: float = 2.0) -> None:
        """Ask every actor for its status (one round, at most ``timeout`` s)."""
        ray = self.cluster.ray
        refs = {(g, j): a.status.remote() for g, copies in enumerate(self.actors)
                for j, a in enumerate(copies)}
        ready, _ = ray.wait(list(refs.values()), num_returns=len(refs), timeout=timeout)
        ready = set(ready)
        for (g, j), ref in refs.items():
            if ref not in ready:  # no answer this round: unknown (not live, not failed)
                self._alive[g][j] = None
                continue
            try:
                st = self.cluster.get(ref, 0.1)
            except Exception:  # the call failed: not live
                self._alive[g][j] = False
                continue
            self._alive[g][j] = st["state"] == "ready"
            self._note(g, st)

    def applied(self, position: int, timeout: float) -> list[dict]:
        """Per group, the status of a copy once it has applied the log up to
        ``position`` (asked now, one live copy of each group, with failover; each
        group's report afterwards).

        Raises
        ------
        ShardUnavailableError
            A group has no copy there within ``timeout`` (restoring, behind, none live).
        """
        got = self.call({g: wire.applied(position, timeout) for g in range(len(self.charts))},
                        timeout + 5.0)
        for g, st in got.items():
            self._note(g, st)
        return [got[g] for g in range(len(self.charts))]

    def call(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """``{group: call}`` (:mod:`.wire`) on one live copy of each group, waited for on
        this thread (see the module doc)."""
        fan = _Fanout(self, calls, timeout)
        pending = {g: fan.submit(g) for g in calls}
        out: dict[int, Any] = {}
        try:
            while pending:
                g, (j, ref) = next(iter(pending.items()))
                del pending[g]
                try:
                    out[g] = fan.answered(g, j, self.cluster.get(ref, fan.left()))
                except Exception as exc:
                    pending[g] = fan.failed(g, j, exc)
        except BaseException:
            fan.cancel(ref for _, ref in pending.values())
            raise
        return out

    async def call_async(self, calls: dict[int, ShardCall], timeout: float) -> dict[int, Any]:
        """:meth:`call` awaited on the event loop: the calls are submitted at once and
        their results awaited (Ray's object refs are awaitable), with the same failover;
        nothing blocks the loop but the submission (Ray's serialisation of the arguments:
        for small calls only)."""
        fan = _Fanout(self, calls, timeout)
        first = {g: fan.submit(g) for g in calls}
        live: dict[int, Any] = {}

        async def one(g: int):
            j, ref = first[g]
            while True:
                live[g] = ref
                try:
                    return g, fan.answered(g, j, await self.cluster.aget(ref, fan.left()))
                except Exception as exc:
                    j, ref = fan.failed(g, j, exc)

        tasks = [asyncio.ensure_future(one(g)) for g in calls]
        try:
            return dict(await asyncio.gather(*tasks))
        except BaseException:
            for t in tasks:
                t.cancel()
            fan.cancel(live.values())
            raise

    def _order(self, g: int) -> list[int]:
        """The copies of group ``g`` in rotation: those heard from alive first, then
        those not heard from yet, then those that failed."""
        n = len(self.actors[g])
        start = self._next[g]
        self._next[g] = (start + 1) % n
        rot = [(start + i) % n for i in range(n)]
        rank = {True: 0, None: 1, False: 2}
        return sorted(rot, key=lambda j: rank[self._alive[g][j]])

    def _unavailable(self, g: int, last: dict[int, str]) -> ShardUnavailableError:
        head = (f"field {self.field_id}: shard group {g} (charts {list(self.charts[g])}) has no "
                f"live copy of {len(self.actors[g])} now ({last.get(g, 'no answer')})")
        why = None if any(a is True for a in self._alive[g]) else self.cluster.no_room()
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


class _Submit:
    """A copy's actor as :class:`.wire.ShardCalls` whose methods submit the call (a
    query packed, :meth:`.actor.ShardActor.query`) and return Ray's reference to its result."""

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


class _Fanout:
    """One request's calls to a field's groups, one copy of each (:meth:`RayGroups.call`
    and :meth:`RayGroups.call_async` wait for them; this is their failover).

    A copy's answer marks it alive. A copy that is dead, restarting or unreachable
    (marked so), or that answers :class:`~flatserve.service.status.ShardUnavailableError`
    (restoring, behind), is passed over for the group's next copy not tried yet; a
    group with none left fails the request with ``ShardUnavailableError``. Any other
    error of a worker (:class:`~flatserve.service.status.NotReadyError` included) is
    the request's.
    """

    def __init__(self, groups: RayGroups, calls: dict[int, ShardCall], timeout: float) -> None:
        self.groups, self.calls = groups, calls
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
        gr = self.groups
        for j in gr._order(g):
            if j in self.tried[g]:
                continue
            self.tried[g].append(j)
            try:
                return j, self.calls[g].run(_Submit(gr.actors[g][j]))
            except Exception as exc:  # the cluster unreachable
                self.last[g] = f"{type(exc).__name__}: {exc}"
                gr._alive[g][j] = False
        raise gr._unavailable(g, self.last)

    def answered(self, g: int, j: int, result):
        """Copy ``j`` of group ``g`` answered ``result``: its value."""
        self.groups._alive[g][j] = True
        return unpack(result) if self.calls[g].packed else result

    def failed(self, g: int, j: int, exc: Exception) -> tuple[int, Any]:
        """Copy ``j`` of group ``g`` failed with ``exc``: the call on the next copy
        (:meth:`submit`), or ``exc`` raised when it is the worker's own error."""
        if isinstance(exc, ShardUnavailableError):  # restoring, behind, failed: another copy
            self.last[g] = str(exc)
        elif isinstance(exc, NotReadyError) or not isinstance(exc, self.groups.cluster._lost):
            raise exc
        else:
            self.last[g] = f"{type(exc).__name__}: {exc}"
            self.groups._alive[g][j] = False
        return self.submit(g)

    def cancel(self, refs) -> None:
        """The request failed: its calls still running are cancelled."""
        for r in list(refs):
            try:
                self.groups.cluster.ray.cancel(r)
            except Exception:  # already done, or the cluster gone
                pass
