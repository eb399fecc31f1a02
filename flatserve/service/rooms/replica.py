"""The log follower of a replica: applies the shared log's entries in log order.

Every server process is a replica (see :mod:`..log.backend`). After the restore
(each field from its newest snapshot plus its batches up to the log position
the restore read, :meth:`.applier.LogApplier.restore_all`), one thread per
process, the :class:`Follower`, reads the log after that position and has its
:class:`~.applier.LogApplier` apply ``create``, ``delete``, ``batch`` and
``snapshot`` entries one by one, in log order, whichever replica committed
them. Its own uploads too: an upload
commits its batch and hands the batch it already charted to the follower
(:meth:`Follower.hand_over`, so it is not charted twice); a ``wait=true``
upload then waits until the follower has applied its position. All replicas
apply the same entries through the same code (chart, then insert in slices of
``insert_slice_rows``), so replicas at the same position hold bit-identical
fields, duplicates included.

``applied`` is the position up to which every entry is applied; reads with a
``min_position`` wait for it (:meth:`Follower.wait_position`), and a write's
request for its own commit (:meth:`Follower.await_applied`). The follower
wakes at once on this process's own commits, else within ``log_poll_interval``
(:meth:`..log.backend.LogBackend.wait_for_change`).

A cluster's shard worker (:mod:`..cluster.worker.shard`) is a follower too, over an
applier restricted to one field and its charts: the same loop, the same
retries; it holds the follower at a log position while its snapshot parts are
stored (:meth:`Follower.held`).

This module knows no SQL: the backend is behind :class:`..log.backend.LogBackend`.
"""
from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

from ...field import AddResult, PreparedBatch
from .applier import LogApplier, Stopped
from ..log.backend import LogBackend
from ..log.rows import LogEntry
from ..status import InvalidParameterError, NotReadyError, ReplicaBehindError, StorageError

log = logging.getLogger("flatserve.service")

#: entries read from the log at a time
READ_CHUNK = 256
#: longest sleep between two looks at the log when nothing wakes the follower
IDLE_WAIT_S = 1.0


@dataclass(frozen=True)
class Handoff:
    """A batch this process committed and already charted (see the module doc)."""

    field_id: int
    seq: int
    prepared: PreparedBatch
    #: a wait=true upload waits for the result of its insert
    want_result: bool


class Follower:
    """The thread that applies the log to this replica's fields (see the module doc).

    Parameters
    ----------
    backend : LogBackend
        The shared log.
    applier : LogApplier
        Applies each entry (owned by the follower: it stops with it).
    """

    def __init__(self, backend: LogBackend, applier: LogApplier) -> None:
        self.applier = applier
        self.backend = backend
        #: every entry up to this position is applied
        self.applied = 0
        #: no entry after this position is applied (:meth:`held`), and the entry
        #: being applied now
        self._hold: int | None = None
        self._applying: int | None = None
        self._cond = threading.Condition()
        self._handoff: dict[int, Handoff] = {}
        self._results: dict[int, tuple[AddResult | None, str | None]] = {}
        self._thread: threading.Thread | None = None
        self._stop = False
        self.started = threading.Event()

    # -- life cycle -------------------------------------------------------------------------
    def restore_and_follow(self) -> None:
        """Restore every stored field (:meth:`.applier.LogApplier.restore_all`), then
        follow the log from the head the restore read; the catalogue is then ready."""
        head = self.applier.restore_all()
        if head is None or self._stop:
            return
        self.start(head)
        self.applier.catalogue.ready.set()
        log.info("ready: %d field(s) loaded; following the log from position %d",
                 len(self.applier.catalogue.entries()), head)

    def start(self, position: int) -> None:
        """Follow the log from ``position`` (every entry up to it is applied)."""
        with self._cond:
            self.applied = position
            self._cond.notify_all()
        t = threading.Thread(target=self._run, name="flatserve-follower", daemon=True)
        t.start()
        self._thread = t  # (only once started: a shutdown meanwhile joins nothing)
        self.started.set()

    @property
    def running(self) -> bool:
        t = self._thread
        return t is not None and t.is_alive() and not self._stop

    def stop(self, drain_timeout: float) -> bool:
        """Apply what is committed now for up to ``drain_timeout`` seconds, then stop
        (the rest is applied from the log on the next start). True if drained."""
        drained = True
        if self.running:
            try:
                target = self.backend.head()
            except StorageError:
                target = self.applied
            drained = self.wait_applied(target, drain_timeout)
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self.applier.stop()
        self.backend.wake()
        return drained

    @contextmanager
    def held(self, position: int) -> Iterator[None]:
        """``with``: no entry after log ``position`` is applied meanwhile (an entry
        after it being applied as this begins is finished first); one holder at a
        time (the caller's to ensure)."""
        with self._cond:
            self._hold = position
            while self._applying is not None and self._applying > position and \
                    not self._stop:
                self._cond.wait(0.5)
        try:
            yield
        finally:
            with self._cond:
                self._hold = None
                self._cond.notify_all()

    def join(self, timeout: float) -> None:
        t = self._thread
        if t is not None:
            t.join(timeout)

    # -- hand-over of this process's batches --------------------------------------------------
    def hand_over(self, position: int, field_id: int, seq: int, prepared: PreparedBatch,
                  want_result: bool) -> None:
        """Called by an upload inside its commit: the batch at ``position`` is charted
        already (:meth:`take_back` if the commit fails)."""
        with self._cond:
            self._handoff[position] = Handoff(field_id, seq, prepared, want_result)

    def take_back(self, position: int) -> None:
        with self._cond:
            self._handoff.pop(position, None)

    def take_result(self, position: int) -> tuple[AddResult | None, str | None]:
        """``(AddResult, None)`` of an applied hand-over that wanted it, ``(None,
        why)`` if its insert failed, ``(None, None)`` if it was not inserted (the
        field was deleted)."""
        with self._cond:
            return self._results.pop(position, (None, None))

    # -- waiting ----------------------------------------------------------------------------
    def wait_applied(self, position: int, timeout: float | None = None) -> bool:
        """Block until every entry up to ``position`` is applied (True), or
        ``timeout`` seconds passed, or the follower stopped (False)."""
        end = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self.applied < position:
                if self._stop or (self.started.is_set() and not self.running):
                    return False
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left if left is not None else 1.0)
        return True

    def wait_position(self, position: int, timeout: float | None) -> None:
        """A read's ``min_position``: return once ``position`` is applied here.

        Raises
        ------
        InvalidParameterError
            ``position`` is beyond the log's head: no write returned it (422).
        ReplicaBehindError
            Not applied within ``timeout`` seconds (or the replica is stopping).
        """
        if self.applied >= position:
            return
        head = self.backend.head()
        if position > head:  # a write's position is committed, so never beyond the head
            raise InvalidParameterError(
                f"min_position: {position} is beyond the log's last position {head}: no "
                "write returned it (pass the position of an upload's response or of a "
                "Flatserve-Position header)", "min_position")
        if not self.wait_applied(position, timeout):
            raise ReplicaBehindError(
                f"this replica has applied the log up to position {self.applied}, "
                f"not yet {position} (waited {timeout or 0:g} s, FLATSERVE_READ_WAIT_TIMEOUT); "
                "retry shortly")

    def await_applied(self, position: int, what: str, timeout: float) -> None:
        """A write's request: wait until its own commit at ``position`` is applied
        here, for up to ``timeout`` seconds (a database outage, a follower held
        up) and not past a shutdown.

        Raises
        ------
        NotReadyError
            Not applied by then (503 with Retry-After): the write IS stored.
        """
        if not self.wait_applied(position, timeout):
            raise NotReadyError(
                f"{what} is stored (log position {position}) but not yet applied on this "
                f"replica (it has applied up to position {self.applied}; waited at "
                f"most {timeout:g} s, FLATSERVE_APPLY_WAIT_TIMEOUT, or the server is "
                "stopping): retry shortly (an upload retried with the same Idempotency-Key "
                "gets its response)")

    def wait_all_committed(self, timeout: float) -> bool:
        """Block until every entry committed so far (any replica's) is applied here;
        False if the follower stops first or ``timeout`` seconds pass."""
        return self.wait_applied(self.backend.head(), timeout)

    @property
    def backend_kind(self) -> str:
        """Where the log is: ``sqlite`` or ``postgresql``."""
        return self.backend.kind

    def progress(self) -> dict:
        """:meth:`lag`, or before the follower started ``{"position": None, "head", ...}``.

        Raises
        ------
        StorageError
            The database is unreachable.
        """
        if self.started.is_set():
            return self.lag()
        return {"position": None, "head": self.backend.head(), "lag_entries": None,
                "lag_seconds": None}

    def lag(self) -> dict:
        """``{"position", "head", "lag_entries", "lag_seconds"}``: this replica's applied
        position, the log's head, and how far behind it is (seconds since the
        first entry not applied here was committed; 0 when caught up)."""
        applied = self.applied
        head = self.backend.head()
        seconds = 0.0
        if head > applied:
            nxt = self.backend.read_log(applied, 1)
            if nxt:
                seconds = max(0.0, time.time() - nxt[0].committed)
        return {"position": applied, "head": head, "lag_entries": max(0, head - applied),
                "lag_seconds": seconds}

    # -- the loop -----------------------------------------------------------------------------
    def _run(self) -> None:
        failures = 0
        while not self._stop:
            try:
                entries = self.backend.read_log(self.applied, READ_CHUNK)
                if not entries:
                    self.backend.wait_for_change(IDLE_WAIT_S)
                    continue
                self.applier.note_pending(entries)
                for entry in entries:
                    with self._cond:
                        while self._hold is not None and entry.position > self._hold and \
                                not self._stop:
                            self._cond.wait(0.5)
                        if self._stop:
                            return
                        self._applying = entry.position
                    try:
                        self._apply(entry)
                    except (Stopped, StorageError):
                        raise
                    except Exception as exc:  # a bug, or an entry this code cannot apply:
                        # the field is marked failed (503 naming it), the others go on
                        log.exception("log entry %d (%s of field %d) cannot be applied",
                                      entry.position, entry.kind, entry.field_id)
                        self.applier.fail_field(entry.field_id, f"log entry {entry.position} "
                                                            f"could not be applied: {exc}")
                    with self._cond:
                        self.applied, self._applying = entry.position, None
                        self._cond.notify_all()
                failures = 0
            except Stopped:
                return
            except Exception as exc:  # the database is unreachable: retry, never skip
                with self._cond:
                    self._applying = None
                    self._cond.notify_all()
                if self._stop:
                    return
                failures += 1
                log.warning("log follower: %s; retrying (applied up to position %d)", exc,
                            self.applied)
                time.sleep(min(1.0, 0.05 * failures))

    def _apply(self, entry: LogEntry) -> None:
        ap = self.applier
        if entry.kind == "batch":
            with self._cond:
                h = self._handoff.pop(entry.position, None)
            if h is not None and (h.field_id, h.seq) != (entry.field_id, entry.seq):
                h = None  # (a commit that failed left it; the entry is another batch)
            # (AddResult, None), (None, why) if the insert failed (the field was rebuilt),
            # (None, None) if not inserted; a storage error propagates: retried
            res = ap.apply_batch(entry, h.prepared if h else None)
            if h is not None and h.want_result:
                with self._cond:
                    self._results[entry.position] = res
        elif entry.kind == "create":
            ap.apply_create(entry)
        elif entry.kind == "delete":
            ap.apply_delete(entry)
        elif entry.kind == "snapshot":
            ap.apply_snapshot(entry)
        else:  # pragma: no cover - a newer server's entry
            log.warning("log entry %d: unknown kind %r skipped", entry.position, entry.kind)
