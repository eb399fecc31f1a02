"""The fields a server holds: names, create, delete, restore on start, queries
and snapshots. Uploads are in :mod:`.uploads`, the background insert of
``wait=false`` batches in :mod:`.indexer`, one field's state in :mod:`.entry`.

Restore: every stored field is registered (state ``loading``), then restored
one by one from its newest snapshot plus the batches committed after it.
A field whose in-memory state may disagree with storage (an insert failed
half-way) is reloaded the same way in the background.
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from ..atlas import AtlasField
from ..basis import Basis
from ..errors import (FieldExistsError, FieldNotFoundError, InvalidInputError, NotReadyError,
                      StorageError, TooManyFieldsError)
from ..field import Field, PreparedBatch, QueryResult
from ..flats import Flats
from .entry import FieldEntry, FieldSpec
from .settings import Settings
from .storage import FieldRow, Storage

log = logging.getLogger("flatserve.service")

PROGRESS_EVERY_S = 2.0
#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048
#: on shutdown, keep indexing pending batches this long; the rest are replayed on start
DRAIN_TIMEOUT_S = 10.0


def stored_flats(e: FieldEntry, form: str, arrays: dict) -> Flats:
    """The :class:`Flats` of a stored batch (its arrays by name)."""
    return Flats.from_arrays(arrays, k=e.spec.k, d=e.spec.d, form=form)


class Registry:
    """Named fields, their storage and their background work."""

    def __init__(self, settings: Settings, storage: Storage, metrics=None):
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._entries: dict[str, FieldEntry] = {}
        #: names being created (their commit runs without holding ``_lock``)
        self._creating: set[str] = set()
        self._lock = threading.Lock()
        self.ready = threading.Event()
        self._bg = ThreadPoolExecutor(1, thread_name_prefix="flatserve-bg")
        #: commits of wait=false uploads, overlapped with their coordinates
        self.commit_pool = ThreadPoolExecutor(2, thread_name_prefix="flatserve-commit")
        self.closed = False

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
        try:
            fid = self.storage.create_field(name, spec.to_dict(),
                                            {"Q": basis.Q, "r": basis.r})
            e = FieldEntry(fid, name, spec, basis, field=fld, state="ready")
            with self._lock:
                self._entries[name] = e
        finally:
            with self._lock:
                self._creating.discard(name)
        log.info("created field %r (k=%d, d=%d, channels=%d)", name, spec.k, spec.d,
                 spec.channels)
        return e

    def delete(self, name: str) -> None:
        e = self.get(name, need_ready=False)
        with e.upload_lock, e.index_lock:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {name!r}")
            self.storage.delete_field(e.id)
            e.deleted = True
            e.indexer.clear()
            with self._lock:
                if self._entries.get(name) is e:
                    del self._entries[name]
        log.info("deleted field %r", name)

    # -- restore ----------------------------------------------------------
    def load_stored(self) -> None:
        """Register every stored field (state ``loading``), then restore them."""
        rows = self.storage.fields()
        orphans = self.storage.clean_orphans()
        if orphans:
            log.info("removed %d unreferenced snapshot file(s)", orphans)
        entries = []
        with self._lock:
            for row in rows:
                spec = FieldSpec.from_dict(row.spec)
                basis = Basis(row.basis["Q"], row.basis["r"], spec.k)
                e = FieldEntry(row.id, row.name, spec, basis, row.created, row.snapshot_file,
                               row.snapshot_seq)
                self._entries[row.name] = e
                entries.append((e, row))
        log.info("restoring %d stored field(s) from %s", len(entries), self.storage.data_dir)
        # fields restore independently: each is ready as soon as it is loaded, and an
        # expensive one holds up only its own thread
        with ThreadPoolExecutor(self.settings.restore_threads,
                                thread_name_prefix="flatserve-restore") as pool:
            for e, row in entries:
                pool.submit(lambda e=e, row=row: None if self.closed else self._restore(e, row))
        if self.closed:
            return
        self.ready.set()
        log.info("ready: %d field(s) loaded", len(entries))

    def _load_snapshot(self, e: FieldEntry, row: FieldRow) -> tuple[Field | AtlasField | None, int]:
        """The field of the row's snapshot and its last batch, or ``(None, 0)``."""
        if not row.snapshot_file:
            return None, 0
        path = self.storage.snapshot_path(row.snapshot_file)
        t0 = time.perf_counter()
        try:
            fld = e.spec.load_field(path)
        except Exception as exc:  # corrupt/missing snapshot: rebuild from batches
            log.warning("field %r: snapshot %s unusable (%s); rebuilding from batches",
                        e.name, path, exc)
            return None, 0
        log.info("field %r: snapshot after batch %d loaded (%d samples) in %.2f s",
                 e.name, row.snapshot_seq, fld.nsamples, time.perf_counter() - t0)
        return fld, row.snapshot_seq

    def _restore(self, e: FieldEntry, row: FieldRow) -> None:
        t0 = time.perf_counter()
        try:
            fld, start = self._load_snapshot(e, row)
            if fld is None:
                fld = e.spec.new_field(e.basis)
            nb, _, _, last = self.storage.batch_stats(e.id)
            todo = [b for b in self.storage.batches(e.id) if b.seq > start]
            log.info("field %r: replaying %d of %d stored batch(es)", e.name, len(todo), nb)
            done, tlast, replayed = 0, time.perf_counter(), 0
            for seq, form, arrays in self.storage.iter_batch_arrays(e.id, start):
                values = arrays.pop("values")
                replayed += int(fld.add(stored_flats(e, form, arrays), values).accepted)
                done += 1
                if time.perf_counter() - tlast > PROGRESS_EVERY_S:
                    log.info("field %r: replayed %d/%d batches (%d samples)", e.name, done,
                             len(todo), fld.nsamples)
                    tlast = time.perf_counter()
            e.field = fld
            e.last_seq = e.indexed_seq = max(last, start)
            e.snapshot_seq = start
            e.new_samples = replayed
            e.state, e.error = "ready", None
            log.info("field %r: restored, %d samples, %d batches replayed in %.2f s", e.name,
                     fld.nsamples, done, time.perf_counter() - t0)
            self.maybe_snapshot(e)
        except Exception as exc:
            log.exception("field %r: restore failed", e.name)
            e.state, e.error = "failed", str(exc)

    def reload(self, e: FieldEntry, why: str) -> None:
        """Rebuild a field from storage in the background (memory may disagree with it)."""
        e.state, e.error = "loading", why
        e.indexer.clear()
        if not self.closed:
            self._bg.submit(self._reload, e)

    def _reload(self, e: FieldEntry) -> None:
        try:
            row = self.storage.field(e.id)
        except Exception as exc:
            e.state, e.error = "failed", str(exc)
            return
        with e.upload_lock, e.index_lock:
            e.indexer.clear()
            self._restore(e, row)

    # -- indexing ---------------------------------------------------------
    def index(self, e: FieldEntry, seq: int, batch: PreparedBatch) -> bool:
        """Insert pending batch ``seq`` (the indexer's work); False stops the indexer."""
        if e.state != "ready" or self.closed:
            return False
        self._before_index(e, seq)
        try:
            with e.index_lock:
                if e.deleted:
                    return False
                if seq > e.indexed_seq:  # (a reload may have replayed it already)
                    e.field.insert_prepared(batch,
                                            slice_rows=self.settings.insert_slice_rows)
                    e.indexed_seq = seq
                    e.new_samples += batch.accepted
                    if self.metrics is not None and batch.accepted:
                        self.metrics.samples_accepted.labels(e.name).inc(batch.accepted)
        except Exception as exc:
            # memory may hold part of the batch: rebuild the field from storage,
            # which holds every committed batch (the reload indexes them all)
            log.exception("field %r: indexing batch %d failed; reloading", e.name, seq)
            self.reload(e, f"reloading after indexing failure: {exc}")
            return False
        self.maybe_snapshot(e)
        return True

    @staticmethod
    def _before_index(e: FieldEntry, seq: int) -> None:
        """Called by the indexer before it takes the field's locks (a test hook)."""

    def wait_indexed(self, e: FieldEntry, seq: int | None = None,
                     timeout: float | None = None) -> bool:
        """Block until batch ``seq`` (default: every acknowledged batch) is indexed."""
        target = e.last_seq if seq is None else seq
        return e.indexer.wait(target, timeout,
                              alive=lambda: e.state == "ready" and not e.deleted)

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
                "charts, whose sample ids and weights the service does not return", "weights")
        res = e.field.query(flats, **kw)
        if res is None:
            return None
        if self.metrics is not None:
            self.metrics.queries.labels(e.name).inc()
            self.metrics.query_rows.labels(e.name).inc(len(res.inside))
        return res

    # -- snapshots --------------------------------------------------------
    def maybe_snapshot(self, e: FieldEntry) -> None:
        every = self.settings.snapshot_every
        if not every or e.new_samples < every or e.snapshot_pending or self.closed:
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
        except Exception:
            log.exception("field %r: background snapshot failed", e.name)
        finally:
            e.snapshot_pending = False

    def snapshot(self, e: FieldEntry) -> dict:
        """Write a snapshot now (uploads wait; queries go on)."""
        t0 = time.perf_counter()
        with e.index_lock:  # the field cannot change meanwhile; queries go on
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            if e.state != "ready":
                raise StorageError(f"field {e.name!r} is not ready ({e.state})")
            seq = e.indexed_seq  # only indexed batches are in the snapshot
            if e.snapshot_file and e.snapshot_seq == seq and \
                    self.storage.snapshot_bytes(e.snapshot_file):
                return {"batch": seq, "bytes": self.storage.snapshot_bytes(e.snapshot_file),
                        "seconds": 0.0}
            path = self.storage.write_snapshot(e.id, seq, lambda p: e.field.save(p))
            e.snapshot_file, e.snapshot_seq, e.new_samples = path.name, seq, 0
        dt = time.perf_counter() - t0
        size = path.stat().st_size
        log.info("field %r: snapshot after batch %d written (%d bytes, %.2f s)", e.name, seq,
                 size, dt)
        if self.metrics is not None:
            self.metrics.snapshots.labels(e.name).inc()
        return {"batch": seq, "bytes": size, "seconds": dt}

    def close(self, drain_timeout: float | None = None) -> None:
        """Stop: index pending batches for up to ``drain_timeout`` seconds (default
        :data:`DRAIN_TIMEOUT_S`; the rest are committed and replayed on the next
        start), stop background work."""
        end = time.monotonic() + (DRAIN_TIMEOUT_S if drain_timeout is None else drain_timeout)
        for e in self.snapshot_entries():
            left = max(0.0, end - time.monotonic())
            if not self.wait_indexed(e, timeout=left):
                log.warning("field %r: %d batch(es) not indexed at shutdown; they are "
                            "stored and will be replayed on start", e.name, e.indexer.counts()[0])
            e.indexer.stop()
        self.closed = True
        self.commit_pool.shutdown(wait=True)
        self._bg.shutdown(wait=True, cancel_futures=True)
        for e in self.snapshot_entries():
            e.indexer.join(max(0.0, end - time.monotonic()) + 1.0)
