"""The background indexer of one field: acknowledged batches waiting for their
Delaunay insert (uploads with ``wait=false``), inserted in commit order.

The queue holds ``(seq, PreparedBatch)``; the counts shown by describe
(pending batches and samples) are derived from it. The insert itself is the
caller's (the registry passes it in), so this module knows nothing of storage.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

from ..field import PreparedBatch


class Indexer:
    """Pending batches of one field and the thread that inserts them."""

    def __init__(self) -> None:
        self._pending: deque[tuple[int, PreparedBatch]] = deque()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stopped = False

    # -- state -----------------------------------------------------------------
    def counts(self) -> tuple[int, int]:
        """``(pending batches, their accepted samples)``."""
        with self._cond:
            return len(self._pending), sum(p.accepted for _, p in self._pending)

    @property
    def running(self) -> bool:
        return self._thread is not None

    # -- producer --------------------------------------------------------------
    def enqueue(self, seq: int, batch: PreparedBatch, insert: Callable[[int, PreparedBatch], bool],
                name: str) -> None:
        """Queue batch ``seq``; start the thread if idle. ``insert(seq, batch)``
        inserts one batch and returns False to stop the thread (the field is
        being reloaded, deleted, or the server stops)."""
        with self._cond:
            self._pending.append((seq, batch))
            if self._thread is None and not self._stopped:
                self._start(insert, name)

    def _start(self, insert, name: str) -> None:
        # (under the condition)
        self._thread = threading.Thread(target=self._run, args=(insert, name),
                                        name=f"flatserve-index-{name}", daemon=True)
        self._thread.start()

    def _run(self, insert, name: str) -> None:
        while True:
            with self._cond:
                if not self._pending or self._stopped:
                    self._thread = None
                    self._cond.notify_all()
                    return
                seq, batch = self._pending[0]
            try:
                go_on = insert(seq, batch)
            except BaseException:
                go_on = False
            with self._cond:
                if self._pending and self._pending[0][0] == seq:
                    self._pending.popleft()
                self._cond.notify_all()
                if not go_on:
                    self._thread = None
                    # batches queued meanwhile (after the reload this stop asked for:
                    # uploads wait for it) were not seen by enqueue, which found this
                    # thread still running: they get a thread of their own
                    if self._pending and not self._stopped:
                        self._start(insert, name)
                    return

    # -- consumers -------------------------------------------------------------
    def wait(self, target: int, timeout: float | None = None, *, alive=lambda: True) -> bool:
        """Block until no pending batch has ``seq <= target``; False on timeout,
        or when the thread stopped with such batches left (shutdown: they are
        replayed on the next start). ``alive()`` False ends the wait (True)."""
        end = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._pending and self._pending[0][0] <= target and alive():
                if self._thread is None:
                    return False
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def clear(self) -> None:
        """Forget every pending batch (a reload replays them from storage)."""
        with self._cond:
            self._pending.clear()
            self._cond.notify_all()

    def stop(self) -> None:
        """No new thread; the running one stops after its current batch."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def join(self, timeout: float) -> None:
        t = self._thread
        if t is not None:
            t.join(timeout)
