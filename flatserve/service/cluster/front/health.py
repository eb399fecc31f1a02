"""What a front knows of its shard actors: :class:`GroupHealth` (per field, each copy's
liveness and each group's newest report) and :class:`StatusRound` (the thread that
asks every actor for its status each :data:`~..worker.actor.STATUS_EVERY_S` and reads
the cluster's free resources, so that a 503 names what would give a shard room).
"""
from __future__ import annotations

import logging
import threading
from typing import Callable

from ...status import ShardUnavailableError
from .. import wire
from ..ray_env import probe_address
from .transport import RayTransport
from ..worker.actor import STATUS_EVERY_S

log = logging.getLogger("flatserve.service.cluster")


class GroupHealth:
    """The liveness of a field's copies (``ncopies``: per group) and its groups' newest
    reports. A copy is alive (True) once its last status or call answered, ready;
    False once its last call failed or it was not ready; None (not counted live)
    while not heard from, or silent in the last status round."""

    def __init__(self, ncopies: list[int]) -> None:
        self.reports: list[dict | None] = [None] * len(ncopies)
        self.alive: list[list[bool | None]] = [[None] * n for n in ncopies]
        #: per group, per copy: the node its last status named (None: not heard from)
        self.nodes: list[list[str | None]] = [[None] * n for n in ncopies]
        self._next = [0] * len(ncopies)

    def add_copy(self, g: int) -> None:
        """Group ``g`` has one more copy (not heard from yet)."""
        self.alive[g] = [*self.alive[g], None]
        self.nodes[g] = [*self.nodes[g], None]

    def note(self, g: int, st: dict) -> None:
        """A copy of group ``g`` reported ``st``: the group's report unless an earlier
        one was further on in the log."""
        old = self.reports[g]
        if old is None or st["through"] >= old["through"]:
            self.reports[g] = st

    def mark(self, g: int, j: int, alive: bool | None) -> None:
        self.alive[g][j] = alive

    def idle(self, g: int) -> bool:
        """Group ``g`` has no copy known live."""
        return not any(a is True for a in self.alive[g])

    def live(self, g: int) -> int:
        return sum(a is True for a in self.alive[g])

    def order(self, g: int) -> list[int]:
        """The copies of group ``g`` in rotation: those heard from alive first, then
        those not heard from yet, then those that failed."""
        n = len(self.alive[g])
        start = self._next[g]
        self._next[g] = (start + 1) % n
        rot = [(start + i) % n for i in range(n)]
        rank = {True: 0, None: 1, False: 2}
        return sorted(rot, key=lambda j: rank[self.alive[g][j]])

    def refresh(self, transport: RayTransport, actors: list[list], timeout: float = 2.0) -> None:
        """Ask every actor (``actors[g][j]``) for its status: one round, at most
        ``timeout`` s."""
        call = wire.status()
        refs = {(g, j): transport.submit(a, call) for g, copies in enumerate(actors)
                for j, a in enumerate(copies)}
        ready, _ = transport.ray.wait(list(refs.values()), num_returns=len(refs),
                                      timeout=timeout)
        ready = set(ready)
        for (g, j), ref in refs.items():
            if ref not in ready:  # no answer this round: unknown (not live, not failed)
                self.alive[g][j] = None
                continue
            try:
                st = transport.result(call, transport.get(ref, 0.1))
            except Exception:  # the call failed: not live
                self.alive[g][j] = False
                continue
            self.alive[g][j] = st["state"] == "ready"
            self.nodes[g][j] = st.get("node")
            self.note(g, st)


class StatusRound:
    """The front's status round, in a thread of its own: each field's refresh (the
    callables ``fields()`` gives), then the cluster's free resources (:attr:`free`;
    None while unknown); the cluster at ``address`` is probed each round (a cluster
    gone is logged once)."""

    def __init__(self, ray, address: str, fields: Callable[[], list[Callable[[], None]]]) -> None:
        self.ray, self.address, self.fields = ray, address, fields
        self.free: dict | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="flatserve-shard-status",
                                        daemon=True)
        self._thread.start()

    def no_room(self, need: dict[str, float], memory: int) -> str | None:
        """Why a shard that runs nowhere (it needs ``need`` of a node's resources)
        cannot be placed now, with what would fix it, or None (room, or nothing known).
        From the last round's figures: no call to the cluster (a query's 503 may be
        made on the event loop)."""
        free = self.free
        if free is None or all(free.get(r, 0) >= v for r, v in need.items()):
            return None
        return (f"no live node has room for it: a shard reserves ray_shard_memory "
                f"{memory:,} bytes of a node's memory resource and the live nodes "
                f"have {int(free.get('memory', 0)):,} bytes free in all; add a node, start the "
                "nodes with a larger --memory, lower FLATSERVE_RAY_SHARD_MEMORY or "
                "FLATSERVE_RAY_SHARDS, or delete a field")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        lost = False
        while not self._stop.wait(STATUS_EVERY_S):
            for refresh in self.fields():
                try:
                    refresh()
                except Exception:  # the cluster unreachable: the next round tries again
                    log.debug("status round failed", exc_info=True)
            try:
                probe_address(self.address, timeout=2.0)
                try:
                    self.free = dict(self.ray.available_resources())
                except Exception:  # pragma: no cover - lost between the probe and the call
                    self.free = None
                if lost:
                    log.warning("the Ray cluster at %s answers again", self.address)
                lost = False
            except ShardUnavailableError as exc:
                self.free = None
                if not lost:
                    log.error("%s: queries answer 503 meanwhile; Ray ends this front after its "
                              "reconnect timeout (RAY_gcs_rpc_server_reconnect_timeout_s, 60 s by "
                              "default), for its supervisor to start it again once the cluster "
                              "is back", exc)
                lost = True
