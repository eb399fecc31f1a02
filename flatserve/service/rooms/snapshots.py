"""The snapshot writer: a field's state written to storage under its snapshot lease.

One room for the snapshot protocol: the field's lease
(:func:`~..log.backend.snapshot_lease`: one writer of a field at a time, across
replicas and within this one; writers of different fields run at once;
renewed while a long snapshot is written; a writer whose lease lapsed abandons
its snapshot, because the new holder's clean-up removes whatever the field does
not point at), the field's lock (held from reading the field's log position until the
field is serialised, never during the database part), background snapshots
every ``snapshot_every`` new samples, and the clean-up of data a dead writer
left. Storage does the writing (:meth:`..log.backend.LogBackend.write_snapshot`).
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Iterator

from ..reports import SnapshotResult
from ..log.backend import LogBackend, lease_owner, snapshot_lease
from ..log.rows import FieldRow
from .catalogue import FieldState
from .entry import FieldEntry
from ..settings import Settings
from ..status import FieldNotFoundError, NotReadyError, StorageError

log = logging.getLogger("flatserve.service")

#: a replica that found a field's snapshot lease taken tries again after this many seconds
SNAPSHOT_RETRY_S = 10.0


class SnapshotWriter:
    """Writes snapshots of this replica's fields (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``snapshot_every``, ``snapshot_lease_seconds``.
    storage : LogBackend
        Holds the fields' snapshot leases, takes the file and points the field at it.
    metrics : Metrics, optional
        Counts the snapshots written per field.
    """

    def __init__(self, settings: Settings, storage: LogBackend, metrics=None) -> None:
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        #: this replica's name in leases (one writer per field here: ``_writing``)
        self.owner = lease_owner()
        #: ids of the fields whose snapshot this replica writes now
        self._writing: set[int] = set()
        self._writing_lock = threading.Lock()
        self._bg = ThreadPoolExecutor(1, thread_name_prefix="flatserve-bg")
        self.closed = False

    # -- the entry's view of its snapshot ---------------------------------------------------
    def adopt(self, e: FieldEntry, row: FieldRow) -> None:
        """Point ``e`` at the stored row's snapshot if it is newer (a ``snapshot`` log
        entry, another replica's)."""
        if row.snapshot_seq >= e.snapshot_seq:
            e.snapshot_file, e.snapshot_seq = row.snapshot_file, row.snapshot_seq
            e.snapshot_position = row.snapshot_position
            e.new_samples = 0

    # -- background snapshots ---------------------------------------------------------------
    def maybe_snapshot(self, e: FieldEntry) -> None:
        """Queue a snapshot of ``e`` if ``snapshot_every`` samples came since its last."""
        every = self.settings.snapshot_every
        if not every or e.new_samples < every or e.snapshot_pending or self.closed or \
                time.monotonic() < e.snapshot_not_before:
            return
        e.snapshot_pending = True
        try:
            self._bg.submit(self._background_snapshot, e)
        except RuntimeError:  # shut down meanwhile
            e.snapshot_pending = False

    def _background_snapshot(self, e: FieldEntry) -> None:
        try:
            if not e.deleted:
                self.snapshot(e)
        except FieldNotFoundError:
            log.info("field %r: deleted before its queued snapshot", e.name)
        except NotReadyError as exc:  # another replica writes one
            log.info("field %r: snapshot skipped: %s", e.name, exc)
            e.snapshot_not_before = time.monotonic() + SNAPSHOT_RETRY_S
        except Exception:
            log.exception("field %r: background snapshot failed", e.name)
        finally:
            e.snapshot_pending = False

    # -- the lease ----------------------------------------------------------------------------
    @contextmanager
    def _lease(self, e: FieldEntry) -> Iterator["_Held"]:
        """Hold field ``e``'s snapshot lease, renewed in a thread, for the ``with``
        block. Within this replica one writer per field (the lease's owner is
        the replica's: a second writer would renew the first's lease, and the
        first to finish would release it under the other).

        Raises
        ------
        NotReadyError
            Another writer (of this replica or another) holds it.
        """
        what = f"field {e.name!r}"
        with self._writing_lock:
            if e.id in self._writing:
                raise NotReadyError(f"a snapshot of {what} is being written by this replica; "
                                    "retry later")
            self._writing.add(e.id)
        try:
            with self._held(e.id, what) as held:
                yield held
        finally:
            with self._writing_lock:
                self._writing.discard(e.id)

    @contextmanager
    def _held(self, field_id: int, what: str) -> Iterator["_Held"]:
        """:meth:`_lease` across replicas: the lease taken, renewed, released."""
        ttl = self.settings.snapshot_lease_seconds
        name = snapshot_lease(field_id)
        if not self.storage.acquire_lease(name, self.owner, ttl):
            raise NotReadyError(f"another replica is writing a snapshot of {what}; retry later")
        held = _Held(self.storage, name, self.owner, ttl)
        renew = threading.Event()

        def renewer():  # keep the lease while a long snapshot is written
            while not renew.wait(ttl / 3):
                try:
                    if not self.storage.renew_lease(name, self.owner, ttl):
                        held.lost.set()
                        log.error("%s: the snapshot lease was taken by another replica while "
                                  "this one wrote; the snapshot is abandoned", what)
                        return
                except StorageError:  # pragma: no cover - retried
                    pass

        th = threading.Thread(target=renewer, name="flatserve-lease", daemon=True)
        th.start()
        try:
            yield held
        finally:
            renew.set()
            th.join()
            try:
                self.storage.release_lease(name, self.owner)
            except StorageError:  # pragma: no cover - it expires
                pass

    # -- writing --------------------------------------------------------------------------------
    def snapshot(self, e: FieldEntry) -> SnapshotResult:
        """Write a snapshot of ``e`` now (uploads and queries go on).

        Raises
        ------
        NotReadyError
            Another writer (of this replica or another) writes one of the field,
            or the lease was lost while writing.
        FieldNotFoundError
            The field was deleted.
        """
        t0 = time.perf_counter()
        with self._lease(e) as lease:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            row = self.storage.field(e.id)  # (a read: outside the field's lock)
            if row.snapshot_file and row.snapshot_seq >= e.indexed_seq and \
                    self.storage.snapshot_bytes(row):
                self.adopt(e, row)
                return SnapshotResult(batch=row.snapshot_seq,
                                      bytes=self.storage.snapshot_bytes(row), written=0,
                                      seconds=0.0)
            known = self.storage.snapshot_parts(e.id)  # (a read: outside the field's lock)
            frozen = _Frozen(e, lease, known)
            try:
                info = self.storage.write_snapshot(e.id, frozen.seq, frozen.pos, frozen.save,
                                                   check=lease.check)
            except BaseException:
                frozen.release()
                self._drop_strays(e, known, lease)
                raise
            finally:
                frozen.release()
            with e.index_lock:
                if frozen.seq >= e.snapshot_seq:
                    e.snapshot_file, e.snapshot_seq = info.file, frozen.seq
                    e.snapshot_position = frozen.pos
                e.new_samples = max(0, e.new_samples - frozen.counted)
        dt = time.perf_counter() - t0
        log.info("field %r: snapshot after batch %d written (%d bytes, %.2f s)", e.name,
                 frozen.seq, info.bytes, dt)
        if self.metrics is not None:
            self.metrics.snapshots.labels(e.name).inc()
        return SnapshotResult(batch=frozen.seq, bytes=self.storage.snapshot_bytes(info.file),
                              written=info.bytes + frozen.stored, seconds=dt)

    def _drop_strays(self, e: FieldEntry, known: set[str], lease: "_Held") -> None:
        """The parts stored during a snapshot that was then abandoned (a cluster's
        shards store their own before the snapshot is written, and one group
        ahead of the others abandons it; a writer that failed after moving its
        parts into place): those the field did not have when the snapshot began.
        Not after the lease was lost: another writer's new parts would look the
        same. Best effort (the field's next snapshot removes what no snapshot
        names)."""
        if lease.lost.is_set():
            return
        try:
            stray = self.storage.snapshot_parts(e.id) - set(known)
            if stray:
                self.storage.remove_parts(e.id, sorted(stray))
                log.info("field %r: removed %d part(s) of an abandoned snapshot", e.name,
                         len(stray))
        except Exception as exc:  # (the field deleted meanwhile, the database away)
            log.warning("field %r: the parts of an abandoned snapshot stay until its next "
                        "snapshot: %s", e.name, exc)

    def clean_orphans(self) -> None:
        """Remove snapshot data left by a writer that died (a live field's under the
        field's lease: never a snapshot another writer is writing;
        :meth:`~..log.backend.LogBackend.clean_orphans`). Best effort."""
        try:
            n = self.storage.clean_orphans()
            if n:
                log.info("removed %d unreferenced snapshot file(s)", n)
        except (StorageError, OSError) as exc:  # best effort: the restore goes on
            log.warning("snapshot clean-up failed: %s", exc)

    def close(self) -> None:
        self.closed = True
        self._bg.shutdown(wait=True, cancel_futures=True)


class _Held:
    """A field's snapshot lease while held: ``check`` raises once it was lost."""

    def __init__(self, storage: LogBackend, name: str, owner: str, ttl: float) -> None:
        self.storage, self.name, self.owner, self.ttl = storage, name, owner, ttl
        self.lost = threading.Event()

    def check(self, renew: bool = True) -> None:
        """Raise unless the lease was held without a break since it was taken
        (``renew``: renewed now, a database round trip). Another replica's clean-up
        may remove what no field points at: a writer that lost it abandons."""
        if self.lost.is_set() or (renew and not self.storage.renew_lease(
                self.name, self.owner, self.ttl)):
            self.lost.set()
            raise NotReadyError("the snapshot lease was lost while writing (another replica "
                                "may hold it); the snapshot is abandoned, retry later")


class _Frozen:
    """A field held still for its snapshot: ``index_lock`` is taken here, with the
    log position it is at, and released once the field is serialised to the
    backend's local file and parts (:meth:`save`, called by the backend) or by
    :meth:`release`, whichever comes first: the follower (every field's entries)
    waits only that long, never during the database part."""

    def __init__(self, e: FieldEntry, lease: _Held, known: set[str]) -> None:
        self.e, self.lease, self.known = e, lease, known
        self.stored = 0
        e.index_lock.acquire()
        self._held = True
        try:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            if e.state is not FieldState.READY:
                raise StorageError(f"field {e.name!r} is not ready ({e.state})")
            self.seq, self.pos = e.indexed_seq, e.indexed_position  # only applied batches
            self.counted = e.new_samples
        except BaseException:
            self.release()
            raise

    def save(self, path, stage) -> list[str]:
        """The field's snapshot file at ``path`` and its changed parts in ``stage``
        (:meth:`~flatserve.contract.SampledField.save_parts`: the parts stored
        already are not written again); the keys of the parts it names."""
        try:
            self.lease.check(renew=False)  # (no database round trip under the field's lock)
            keys = self.e.field.save_parts(path, stage, self.known)
            # parts a field's shards stored themselves (cluster mode), not in ``stage``
            self.stored = self.e.field.stored_bytes
            return keys
        finally:
            self.release()

    def release(self) -> None:
        if self._held:
            self._held = False
            self.e.index_lock.release()
