"""The fields a replica holds: names, create, delete, restore on start, the
application of log entries, queries and snapshots. Uploads are in
:mod:`.uploads`, the log follower in :mod:`.replica`, one field's state in
:mod:`.entry`, storage behind :class:`.backend.LogBackend`.

Restore: the log head and the stored fields are read in one consistent view
(:meth:`.backend.LogBackend.state`); every field is registered (state
``loading``), then restored one by one from its newest snapshot plus its
batches up to that head, and the follower applies the log from there. Every
change of the fields (create, delete, batches) reaches memory through the
follower, in log order, on every replica alike; a write's request commits it
and waits until this replica has applied it. A field whose in-memory state may
disagree with storage (an insert failed half-way) is rebuilt the same way, by
the follower, before it goes on.
"""
from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

from ..atlas_field import AtlasField
from ..basis import Basis
from ..errors import InvalidInputError
from .status import FieldExistsError, FieldNotFoundError, NotReadyError, ReplicaBehindError, StorageError, StorageUnavailableError, TooManyFieldsError
from ..field import AddResult, Field, PreparedBatch, QueryResult
from ..flats import Flats
from .backend import SNAPSHOT_LEASE, FieldRow, LogBackend, LogEntry, SnapshotGoneError
from .entry import FieldEntry, FieldSpec
from .replica import Follower
from .settings import Settings

log = logging.getLogger("flatserve.service")

PROGRESS_EVERY_S = 2.0
#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048
#: on shutdown, keep applying committed entries this long; the rest are applied on start
DRAIN_TIMEOUT_S = 10.0
#: a replica that found the snapshot lease taken tries again after this many seconds
SNAPSHOT_RETRY_S = 10.0
#: a restore that found the database unreachable tries again after this many seconds
RESTORE_RETRY_S = 1.0


def stored_flats(e: FieldEntry, form: str | None, arrays: dict) -> Flats:
    """The :class:`Flats` of a stored batch (its arrays by name; the form is
    inferred from the names when None)."""
    return Flats.from_arrays(arrays, k=e.spec.k, d=e.spec.d, form=form)


def _entry_of(row: FieldRow, state: str = "loading") -> FieldEntry:
    spec = FieldSpec.from_dict(row.spec)
    basis = Basis(row.basis["Q"], row.basis["r"], spec.k)
    return FieldEntry(row.id, row.name, spec, basis, row.created, row.snapshot_file,
                      row.snapshot_seq, state=state, position=row.position,
                      snapshot_position=row.snapshot_position)


def _failed_entry(row: FieldRow, exc: Exception) -> FieldEntry:
    """A stored field whose entry cannot be built (``_entry_of`` raised ``exc``):
    state ``failed``, no basis, its spec's sizes where readable (else 0)."""
    try:
        spec = FieldSpec.from_dict(row.spec)
    except Exception:
        spec = FieldSpec(0, 0, 0, {})
    return FieldEntry(row.id, row.name, spec, None, row.created, row.snapshot_file,
                      row.snapshot_seq, state="failed", position=row.position,
                      error=f"its stored definition cannot be read: {exc}")


class Registry:
    """Named fields of this replica, their storage and their background work."""

    def __init__(self, settings: Settings, storage: LogBackend, metrics=None):
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._entries: dict[str, FieldEntry] = {}
        self._by_id: dict[int, FieldEntry] = {}
        #: names being created (their commit runs without holding ``_lock``)
        self._creating: set[str] = set()
        #: fields this process built for its own create (field id -> Field)
        self._built: dict[int, object] = {}
        self._lock = threading.Lock()
        self.ready = threading.Event()
        self._bg = ThreadPoolExecutor(1, thread_name_prefix="flatserve-bg")
        #: commits of uploads, overlapped with their coordinates
        self.commit_pool = ThreadPoolExecutor(2, thread_name_prefix="flatserve-commit")
        self.follower = Follower(self)
        #: this replica's name in leases
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.closed = False
        self._restore_head = 0

    # -- lookup -----------------------------------------------------------
    def snapshot_entries(self) -> list[FieldEntry]:
        with self._lock:
            return list(self._entries.values())

    def get(self, name: str, *, need_ready: bool = True) -> FieldEntry:
        with self._lock:
            e = self._entries.get(name)
        if e is None:
            if not self.ready.is_set():
                raise NotReadyError("stored fields are still loading; retry shortly")
            raise FieldNotFoundError(f"no field named {name!r}")
        if need_ready and e.state == "loading":
            raise NotReadyError(f"field {name!r} is still loading; retry shortly")
        if need_ready and e.state == "failed":
            raise StorageError(f"field {name!r} could not be loaded: {e.error}")
        return e

    def entry_by_id(self, field_id: int) -> FieldEntry | None:
        with self._lock:
            return self._by_id.get(field_id)

    # -- positions ----------------------------------------------------------
    @property
    def position(self) -> int:
        """The log position this replica has applied."""
        return self.follower.applied

    def wait_position(self, position: int, timeout: float | None) -> None:
        """Return once this replica has applied log ``position``.

        Raises
        ------
        InvalidInputError
            ``position`` is beyond the log's head: no write returned it (422).
        ReplicaBehindError
            Not applied within ``timeout`` seconds (or the replica is stopping).
        """
        if self.follower.applied >= position:
            return
        head = self.storage.head()
        if position > head:  # a write's position is committed, so never beyond the head
            raise InvalidInputError(
                f"min_position: {position} is beyond the log's last position {head}: no "
                "write returned it (pass the position of an upload's response or of a "
                "Flatserve-Position header)", "min_position")
        if not self.follower.wait_applied(position, timeout):
            raise ReplicaBehindError(
                f"this replica has applied the log up to position {self.follower.applied}, "
                f"not yet {position} (waited {timeout or 0:g} s, FLATSERVE_READ_WAIT_TIMEOUT); "
                "retry shortly")

    def await_applied(self, position: int, what: str) -> None:
        """A write's request: wait until this replica applied its own commit at
        ``position``, for up to ``apply_wait_timeout`` seconds (a database outage, a
        follower held up) and not past a shutdown.

        Raises
        ------
        NotReadyError
            Not applied by then (503 with Retry-After): the write IS stored.
        """
        timeout = self.settings.apply_wait_timeout
        if not self.follower.wait_applied(position, timeout):
            raise NotReadyError(
                f"{what} is stored (log position {position}) but not yet applied on this "
                f"replica (it has applied up to position {self.follower.applied}; waited at "
                f"most {timeout:g} s, FLATSERVE_APPLY_WAIT_TIMEOUT, or the server is "
                "stopping): retry shortly (an upload retried with the same Idempotency-Key "
                "gets its response)")

    # -- create / delete --------------------------------------------------
    def create(self, name: str, spec: FieldSpec, basis: Basis) -> FieldEntry:
        fld = spec.new_field(basis)
        with self._lock:  # the name is reserved; the commit runs without the lock
            if name in self._entries or name in self._creating:
                raise FieldExistsError(f"field {name!r} already exists")
            if len(self._entries) + len(self._creating) >= self.settings.max_fields:
                raise TooManyFieldsError(
                    f"this server holds {len(self._entries)} fields; the limit is "
                    f"{self.settings.max_fields}"
                )
            self._creating.add(name)
        fid = None
        try:
            fid, pos = self.storage.create_field(name, spec.to_dict(),
                                                 {"Q": basis.Q, "r": basis.r})
            with self._lock:
                self._built[fid] = fld
            self.await_applied(pos, f"field {name!r}")
            e = self.entry_by_id(fid)
            if e is None:  # deleted meanwhile (by another replica)
                raise FieldNotFoundError(f"field {name!r} was deleted meanwhile")
        finally:
            with self._lock:
                self._creating.discard(name)
                # the follower may have applied the create before the hand-over
                self._built.pop(fid, None)
        log.info("created field %r (k=%d, d=%d, channels=%d) at log position %d", name,
                 spec.k, spec.d, spec.channels, pos)
        return e

    def delete(self, name: str) -> int:
        """Delete a field; the log position of the delete."""
        e = self.get(name, need_ready=False)
        with e.upload_lock:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {name!r}")
            pos = self.storage.delete_field(e.id)
        self.await_applied(pos, f"the delete of {name!r}")
        log.info("deleted field %r at log position %d", name, pos)
        return pos

    # -- applying log entries (the follower's thread) ------------------------
    def note_pending(self, entries: list[LogEntry]) -> None:
        """The follower read these entries: count their batches as pending."""
        for en in entries:
            if en.kind != "batch":
                continue
            e = self.entry_by_id(en.field_id)
            if e is not None:
                with e.pending_lock:
                    e.pending.setdefault(en.position, en.nrows)

    def apply_create(self, entry: LogEntry) -> None:
        try:
            row = self.storage.field(entry.field_id)
        except FieldNotFoundError:
            return  # deleted later in the log: its delete entry follows
        e = _entry_of(row, state="ready")
        with self._lock:
            fld = self._built.pop(row.id, None)
        e.field = fld if fld is not None else e.spec.new_field(e.basis)
        with self._lock:
            old = self._entries.get(e.name)
            if old is not None and old.id != e.id:  # pragma: no cover - a delete skipped
                old.deleted = True
                self._by_id.pop(old.id, None)
            self._entries[e.name] = e
            self._by_id[e.id] = e

    def apply_delete(self, entry: LogEntry) -> None:
        with self._lock:
            e = self._by_id.pop(entry.field_id, None)
            if e is not None and self._entries.get(e.name) is e:
                del self._entries[e.name]
        if e is None:
            return
        with e.index_lock:
            e.deleted = True
        with e.pending_lock:
            e.pending.clear()

    def apply_snapshot(self, entry: LogEntry) -> None:
        e = self.entry_by_id(entry.field_id)
        if e is None:
            return
        try:
            row = self.storage.field(entry.field_id)
        except FieldNotFoundError:
            return
        if row.snapshot_seq >= e.snapshot_seq:
            e.snapshot_file, e.snapshot_seq = row.snapshot_file, row.snapshot_seq
            e.snapshot_position = row.snapshot_position
            e.new_samples = 0

    def apply_batch(self, entry: LogEntry, prepared: PreparedBatch | None, follower
                    ) -> tuple[AddResult | None, str | None]:
        """Insert the batch of a log entry (charting it unless this process did);
        ``(AddResult, None)``, or ``(None, why)`` if the insert failed (the field
        is then rebuilt from storage up to this entry), or ``(None, None)`` if
        there was nothing to insert (field deleted or not held)."""
        e = self.entry_by_id(entry.field_id)
        try:
            if e is None or e.deleted or e.state != "ready" or entry.seq <= e.indexed_seq:
                return None, None
            self._before_index(e, entry.seq)
            follower.check_stop()
            t0 = time.perf_counter()
            if prepared is None:
                try:
                    arrays = dict(self.storage.batch_arrays(e.id, entry.seq))
                except FieldNotFoundError:
                    return None, None  # deleted meanwhile: its delete entry follows
                values = arrays.pop("values")
                prepared = e.field.prepare(stored_flats(e, None, arrays), values)
            try:
                with e.index_lock:
                    if e.deleted:
                        return None, None
                    res = e.field.insert_prepared(prepared,
                                                  slice_rows=self.settings.insert_slice_rows)
                    e.indexed_seq, e.indexed_position = entry.seq, entry.position
                    e.new_samples += res.accepted
            except Exception as exc:
                # memory may hold part of the batch: rebuild the field from storage up
                # to this entry (it holds every committed batch), then go on
                log.exception("field %r: inserting batch %d failed; rebuilding", e.name,
                              entry.seq)
                self.rebuild(e, entry.position, f"rebuilding after a failed insert: {exc}")
                return None, str(exc)
            if self.metrics is not None:
                self.metrics.apply_seconds.observe(time.perf_counter() - t0)
                if res.accepted:
                    self.metrics.samples_accepted.labels(e.name).inc(res.accepted)
        finally:
            if e is not None:
                with e.pending_lock:
                    e.pending.pop(entry.position, None)
        self.maybe_snapshot(e)
        return res, None

    def fail_field(self, field_id: int, why: str) -> None:
        """Mark a field failed (its requests get a 503 naming ``why``)."""
        e = self.entry_by_id(field_id)
        if e is not None:
            e.state, e.error = "failed", why

    @staticmethod
    def _before_index(e: FieldEntry, seq: int) -> None:
        """Called by the follower before it inserts batch ``seq`` of ``e`` (a test hook)."""

    # -- restore ----------------------------------------------------------
    def load_stored(self) -> None:
        """Register every stored field (state ``loading``), restore them to the log
        head read with them, then follow the log."""
        while True:
            try:
                head, rows = self.storage.state()
                break
            except StorageError as exc:  # unreachable: wait for it (never ready otherwise)
                if self.closed:
                    return
                log.warning("restore: %s; retrying in %g s", exc, RESTORE_RETRY_S)
                time.sleep(RESTORE_RETRY_S)
        self._restore_head = head
        self._clean_orphans()
        entries = []
        with self._lock:
            for row in rows:
                try:
                    e = _entry_of(row)
                except Exception as exc:  # (a spec this version cannot read): that field only
                    log.exception("field %r: its stored definition cannot be read", row.name)
                    self._entries[row.name] = self._by_id[row.id] = _failed_entry(row, exc)
                    continue
                self._entries[row.name] = e
                self._by_id[row.id] = e
                entries.append((e, row))
        log.info("restoring %d stored field(s) from %s %s to log position %d", len(entries),
                 self.storage.kind, self.storage.where, head)
        # fields restore independently: each is ready as soon as it is loaded, and an
        # expensive one holds up only its own thread
        with ThreadPoolExecutor(self.settings.restore_threads,
                                thread_name_prefix="flatserve-restore") as pool:
            for e, row in entries:
                pool.submit(lambda e=e, row=row: None if self.closed
                            else self._restore(e, row))
        if self.closed:
            return
        self.follower.start(head)
        self.ready.set()
        log.info("ready: %d field(s) loaded; following the log from position %d",
                 len(entries), head)

    def _clean_orphans(self) -> None:
        """Remove snapshot data left by a writer that died (under the snapshot lease:
        never a snapshot another replica is writing)."""
        try:
            if not self.storage.acquire_lease(SNAPSHOT_LEASE, self.owner, 60.0):
                return
        except StorageError as exc:  # a full disk: nothing to clean now
            log.warning("snapshot clean-up skipped: %s", exc)
            return
        try:
            n = self.storage.clean_orphans()
            if n:
                log.info("removed %d unreferenced snapshot file(s)", n)
        except (StorageError, OSError) as exc:  # best effort: the restore goes on
            log.warning("snapshot clean-up failed: %s", exc)
        finally:
            try:
                self.storage.release_lease(SNAPSHOT_LEASE, self.owner)
            except StorageError:  # pragma: no cover - it expires
                pass

    def _load_snapshot(self, e: FieldEntry, row: FieldRow, upto: int
                       ) -> tuple[Field | AtlasField | None, FieldRow]:
        """The field of the row's snapshot (None if there is none, it is unusable, or
        it holds batches after log position ``upto``: a newer snapshot that replaced
        it meanwhile would carry the field past ``upto``) and the row it came from
        (re-read if the snapshot was replaced meanwhile)."""
        for _ in range(5):
            if not row.snapshot_file or row.snapshot_position > upto:
                return None, row
            t0 = time.perf_counter()
            try:
                fld = self.storage.load_snapshot(row, e.spec.load_field)
            except SnapshotGoneError:
                row = self.storage.field(e.id)  # a newer one replaced it: take that
                continue
            except Exception as exc:  # corrupt/missing snapshot: rebuild from batches
                log.warning("field %r: snapshot %s unusable (%s); rebuilding from batches",
                            e.name, self.storage.snapshot_location(row), exc)
                return None, row
            log.info("field %r: snapshot after batch %d loaded (%d samples) in %.2f s",
                     e.name, row.snapshot_seq, fld.nsamples, time.perf_counter() - t0)
            return fld, row
        return None, row

    def _restore(self, e: FieldEntry, row: FieldRow, upto: int | None = None) -> None:
        """Restore ``e`` to log position ``upto`` (default: the head the start-up
        restore read): its snapshot, then its batches up to ``upto`` inserted as
        the follower inserts them (chart, insert in slices). The database
        unreachable meanwhile: tried again until it answers (or the replica stops)."""
        if upto is None:
            upto = self._restore_head
        while True:
            try:
                return self._restore_once(e, row, upto)
            except StorageUnavailableError as exc:
                if self.closed:
                    e.state, e.error = "failed", str(exc)
                    return
                log.warning("field %r: restore interrupted (%s); retrying in %g s", e.name,
                            exc, RESTORE_RETRY_S)
                time.sleep(RESTORE_RETRY_S)

    def _restore_once(self, e: FieldEntry, row: FieldRow, upto: int) -> None:
        t0 = time.perf_counter()
        try:
            fld, row = self._load_snapshot(e, row, upto)
            start, start_pos = (row.snapshot_seq, row.snapshot_position) if fld is not None \
                else (0, 0)
            if fld is None:
                fld = e.spec.new_field(e.basis)
            todo = self.storage.batches(e.id, after_seq=start, upto_position=upto)
            nb = self.storage.batch_stats(e.id)[0]
            log.info("field %r: replaying %d of %d stored batch(es)", e.name, len(todo), nb)
            done, tlast, replayed = 0, time.perf_counter(), 0
            seq, pos = start, start_pos
            for b in todo:
                arrays = dict(self.storage.batch_arrays(e.id, b.seq))
                values = arrays.pop("values")
                prepared = fld.prepare(stored_flats(e, b.form, arrays), values)
                replayed += int(fld.insert_prepared(
                    prepared, slice_rows=self.settings.insert_slice_rows).accepted)
                seq, pos = b.seq, b.position
                done += 1
                if time.perf_counter() - tlast > PROGRESS_EVERY_S:
                    log.info("field %r: replayed %d/%d batches (%d samples)", e.name, done,
                             len(todo), fld.nsamples)
                    tlast = time.perf_counter()
            e.field = fld
            e.indexed_seq, e.indexed_position = seq, pos
            e.snapshot_file = row.snapshot_file if start else None
            e.snapshot_seq, e.snapshot_position = start, start_pos
            e.new_samples = replayed
            e.state, e.error = "ready", None
            log.info("field %r: restored, %d samples, %d batches replayed in %.2f s", e.name,
                     fld.nsamples, done, time.perf_counter() - t0)
            self.maybe_snapshot(e)
        except StorageUnavailableError:
            raise  # retried by _restore
        except Exception as exc:
            log.exception("field %r: restore failed", e.name)
            e.state, e.error = "failed", str(exc)

    def rebuild(self, e: FieldEntry, upto: int, why: str) -> None:
        """Rebuild a field from storage up to log position ``upto`` (the follower's
        thread: no later entry is applied meanwhile; queries get 503 until done)."""
        e.state, e.error = "loading", why
        while True:
            try:
                row = self.storage.field(e.id)
                break
            except StorageUnavailableError as exc:  # as _restore: wait for the database
                if self.closed:
                    e.state, e.error = "failed", str(exc)
                    return
                time.sleep(RESTORE_RETRY_S)
            except Exception as exc:
                e.state, e.error = "failed", str(exc)
                return
        with e.upload_lock, e.index_lock:
            self._restore(e, row, upto)

    # -- query ------------------------------------------------------------
    def query(self, e: FieldEntry, flats: Flats, **kw) -> "QueryResult | None":
        """Interpolate field ``e`` at ``flats`` (keywords of :meth:`Field.query`;
        ``blocking=False`` gives None instead of waiting for an insert)."""
        if len(flats) < SMALL_QUERY_ROWS:  # not worth starting native worker threads
            kw.setdefault("threads", 1)
        if e.deleted:
            raise FieldNotFoundError(f"no field named {e.name!r}")
        if kw.get("return_weights") and e.spec.is_atlas:
            raise InvalidInputError(
                f"weights: field {e.name!r} is an atlas field: its answers blend several "
                "charts, whose sample ids and weights the service does not return; a field "
                "created with basis {\"kind\": \"tangent_simplex\"} (one chart) returns them",
                "weights")
        res = e.field.query(flats, **kw)
        if res is None:
            return None
        if self.metrics is not None:
            self.metrics.queries.labels(e.name).inc()
            self.metrics.query_rows.labels(e.name).inc(len(res.inside))
        return res

    def wait_all_committed(self) -> bool:
        """Block until this replica has applied every entry committed so far (any
        replica's); False if it stops first or ``apply_wait_timeout`` seconds pass."""
        return self.follower.wait_applied(self.storage.head(),
                                          self.settings.apply_wait_timeout)

    # -- snapshots --------------------------------------------------------
    def maybe_snapshot(self, e: FieldEntry) -> None:
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

    def snapshot(self, e: FieldEntry) -> dict:
        """Write a snapshot now (this replica's field; uploads and queries go on).
        One replica writes at a time (the snapshot lease): NotReadyError if another
        does."""
        t0 = time.perf_counter()
        ttl = self.settings.snapshot_lease_seconds
        if not self.storage.acquire_lease(SNAPSHOT_LEASE, self.owner, ttl):
            raise NotReadyError("another replica is writing a snapshot; retry later")
        renew = threading.Event()
        lost = threading.Event()  # another replica took the lease: do not point at ours

        def renewer():  # keep the lease while a long snapshot is written
            while not renew.wait(ttl / 3):
                try:
                    if not self.storage.renew_lease(SNAPSHOT_LEASE, self.owner, ttl):
                        lost.set()
                        log.error("field %r: the snapshot lease was taken by another replica "
                                  "while this one wrote; the snapshot is abandoned", e.name)
                        return
                except StorageError:  # pragma: no cover - retried
                    pass

        def still_held(renew: bool = True):  # another replica's clean-up may remove
            # what no field points at: held without a break since it was taken, or abandon
            if lost.is_set() or (renew and not self.storage.renew_lease(
                    SNAPSHOT_LEASE, self.owner, ttl)):
                lost.set()
                raise NotReadyError("the snapshot lease was lost while writing (another "
                                    "replica may hold it); the snapshot is abandoned, retry "
                                    "later")

        th = threading.Thread(target=renewer, name="flatserve-lease", daemon=True)
        th.start()
        held = False
        try:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            row = self.storage.field(e.id)  # (a read: outside the field's lock)
            if row.snapshot_file and row.snapshot_seq >= e.indexed_seq and \
                    self.storage.snapshot_bytes(row):
                e.snapshot_file, e.snapshot_seq = row.snapshot_file, row.snapshot_seq
                e.snapshot_position, e.new_samples = row.snapshot_position, 0
                return {"batch": row.snapshot_seq, "bytes": self.storage.snapshot_bytes(row),
                        "seconds": 0.0}
            # index_lock is held from reading the position until the field is
            # serialised to the backend's local file (the snapshot is exactly the state
            # at ``seq`` / ``pos``), and released before the database part of
            # write_snapshot: the follower (every field's entries) waits only that long
            e.index_lock.acquire()
            held = True
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            if e.state != "ready":
                raise StorageError(f"field {e.name!r} is not ready ({e.state})")
            seq, pos = e.indexed_seq, e.indexed_position  # only applied batches
            counted = e.new_samples

            def save(path):
                nonlocal held
                try:
                    still_held(renew=False)  # (no database round trip under the field's lock)
                    e.field.save(path)
                finally:
                    held = False
                    e.index_lock.release()

            info = self.storage.write_snapshot(e.id, seq, pos, save, check=still_held)
            with e.index_lock:
                if seq >= e.snapshot_seq:
                    e.snapshot_file, e.snapshot_seq, e.snapshot_position = info.file, seq, pos
                e.new_samples = max(0, e.new_samples - counted)
        finally:
            if held:
                e.index_lock.release()
            renew.set()
            th.join()
            try:
                self.storage.release_lease(SNAPSHOT_LEASE, self.owner)
            except StorageError:  # pragma: no cover - it expires
                pass
        dt = time.perf_counter() - t0
        log.info("field %r: snapshot after batch %d written (%d bytes, %.2f s)", e.name, seq,
                 info.bytes, dt)
        if self.metrics is not None:
            self.metrics.snapshots.labels(e.name).inc()
        return {"batch": seq, "bytes": info.bytes, "seconds": dt}

    def close(self, drain_timeout: float | None = None) -> None:
        """Stop: apply committed entries for up to ``drain_timeout`` seconds (default
        :data:`DRAIN_TIMEOUT_S`; the rest are applied from the log on the next
        start), stop background work."""
        end = time.monotonic() + (DRAIN_TIMEOUT_S if drain_timeout is None else drain_timeout)
        if not self.follower.stop(max(0.0, end - time.monotonic())):
            log.warning("stopping at log position %d with committed entries not applied; "
                        "they are stored and applied on the next start", self.follower.applied)
        self.closed = True
        self.commit_pool.shutdown(wait=True)
        self._bg.shutdown(wait=True, cancel_futures=True)
        self.follower.join(max(0.0, end - time.monotonic()) + 1.0)
