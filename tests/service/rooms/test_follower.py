"""The log follower's hold (``flatserve/service/rooms/replica.py``, ``Follower.held``): what a
cluster shard worker's snapshot parts rely on, on a log in memory (no storage).

Oracle: the positions the applier was handed, in order, against the hold's position.
"""
from __future__ import annotations

import threading
import time

from flatserve.service.log.rows import LogEntry
from flatserve.service.rooms.replica import Follower


class MemoryLog:
    """The part of :class:`~flatserve.service.log.backend.LogBackend` a follower reads."""

    kind = "memory"

    def __init__(self) -> None:
        self.entries: list[LogEntry] = []
        self._changed = threading.Event()

    def commit(self, n: int) -> None:
        for _ in range(n):
            p = len(self.entries) + 1
            self.entries.append(LogEntry(p, "batch", 1, p, time.time(), 1))
        self._changed.set()

    def head(self) -> int:
        return len(self.entries)

    def read_log(self, after: int, limit: int = 256) -> list[LogEntry]:
        return self.entries[after:after + limit]

    def wait_for_change(self, timeout: float) -> None:
        self._changed.wait(timeout)
        self._changed.clear()

    def wake(self) -> None:
        self._changed.set()


class SlowApplier:
    """Records the positions it applies; each batch takes ``delay`` seconds."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay, self.done = delay, []
        self.started = threading.Event()

    def note_pending(self, entries) -> None:
        pass

    def apply_batch(self, entry, prepared):
        self.started.set()
        time.sleep(self.delay)
        self.done.append(entry.position)
        return None, None

    def stop(self) -> None:
        pass


def _follower(delay: float = 0.0):
    log, ap = MemoryLog(), SlowApplier(delay)
    fo = Follower(log, ap)
    fo.start(0)
    return log, ap, fo


def test_held_applies_nothing_after_its_position_until_released():
    log, ap, fo = _follower()
    try:
        log.commit(3)
        assert fo.wait_applied(3, 10)
        with fo.held(3):
            log.commit(2)
            time.sleep(0.3)
            assert fo.applied == 3 and ap.done == [1, 2, 3]
        assert fo.wait_applied(5, 10) and ap.done == [1, 2, 3, 4, 5]
    finally:
        fo.stop(0)
        fo.join(5)


def test_held_waits_for_an_entry_being_applied_past_its_position():
    """A hold set while the entry after it is being applied begins once that entry is
    applied (the caller then sees it, and a shard worker's snapshot retries), never
    while it is half applied."""
    log, ap, fo = _follower(delay=0.5)
    try:
        log.commit(1)
        assert ap.started.wait(10)
        with fo.held(0):
            assert ap.done == [1] and fo.applied == 1
    finally:
        fo.stop(0)
        fo.join(5)
