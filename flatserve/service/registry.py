"""The fields a server holds: in-memory :class:`flatserve.Field` objects, their
locks, durable storage, restore on start and background snapshots.

Concurrency per field
---------------------
* ``lock`` (readers/writer): queries read, inserts write, so a query never sees
  a half-inserted batch;
* ``upload_lock``: serialises uploads (and snapshots, which must see a field
  that no upload changes) without blocking queries.

* ``index_lock``: serialises changes of the in-memory field (inserts, the
  background indexer, snapshots, reloads).

Durability of an upload (Qdrant's ``wait`` convention):

* ``wait=True`` (default): once every earlier batch is indexed, the batch is
  applied to the in-memory field and its arrays are committed to SQLite under the
  write lock; the response is sent only after the commit. If the commit fails the
  field is reloaded from storage.
* ``wait=False``: the batch is validated, then committed to SQLite (in a
  storage thread) while its coordinates are computed (so the accepted /
  rejected rows and reasons are exact), and the response is sent once both are
  done; the Delaunay insert then happens in the field's
  background indexer, batch by batch in commit order, each whole batch under the
  write lock. ``indexed_seq`` is the last batch in the triangulation; snapshots
  only ever cover indexed batches, and a restart replays every committed batch,
  so nothing acknowledged is lost whenever the process dies.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field as dc_field

import numpy as np

from ..errors import FieldExistsError, FieldNotFoundError, InvalidInputError, StorageError
from .errors import IdempotencyConflictError, NotReadyError, TooManyFieldsError
from .ingest import insert_prepared, prepare
from .rwlock import RWLock
from .settings import Settings
from .storage import FieldRow, Storage, content_hash, pack_arrays

log = logging.getLogger("flatserve.service")

PROGRESS_EVERY_S = 2.0
#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048
#: on shutdown, keep indexing pending batches this long; the rest are replayed on start
DRAIN_TIMEOUT_S = 10.0


def _Field():
    from ..field import Field

    return Field


def _Basis():
    from ..basis import Basis

    return Basis


def apply_batch(fld, form: str, arrays: dict[str, np.ndarray], values: np.ndarray):
    """Insert one batch into a Field (the only place that knows the forms)."""
    if form == "rays":
        return fld.add_rays(arrays["origins"], arrays["directions"], values)
    if form == "parametric":
        return fld.add_parametric(arrays["A"], arrays["b"], values)
    return fld.add(arrays["Q"], arrays["r"], values)


def query_batch(fld, form: str, arrays: dict[str, np.ndarray], **kw):
    if form == "rays":
        return fld.query_rays(arrays["origins"], arrays["directions"], **kw)
    if form == "parametric":
        return fld.query_parametric(arrays["A"], arrays["b"], **kw)
    return fld.query(arrays["Q"], arrays["r"], **kw)


@dataclass(eq=False)
class FieldEntry:
    id: int
    name: str
    spec: dict  # k, d, channels, basis spec, roundtrip_tol
    basis_arrays: dict
    created: float
    snapshot_file: str | None = None
    snapshot_seq: int = 0
    field: object | None = None
    state: str = "loading"
    error: str | None = None
    last_seq: int = 0
    new_samples: int = 0
    snapshot_pending: bool = False
    deleted: bool = False
    lock: RWLock = dc_field(default_factory=RWLock)
    upload_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    index_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    #: last batch inserted into the triangulation (<= last_seq)
    indexed_seq: int = 0
    #: committed, acknowledged batches not yet indexed: (seq, Prepared), commit order
    pending: deque = dc_field(default_factory=deque)
    pending_samples: int = 0
    #: guards ``pending``, ``pending_samples``, ``indexer``; notified on every change
    cond: threading.Condition = dc_field(default_factory=threading.Condition)
    indexer: threading.Thread | None = None
    stop_indexing: bool = False

    @property
    def k(self) -> int:
        return self.spec["k"]

    @property
    def d(self) -> int:
        return self.spec["d"]

    @property
    def channels(self) -> int:
        return self.spec["channels"]


class Registry:
    def __init__(self, settings: Settings, storage: Storage, metrics=None):
        self.settings = settings
        self.storage = storage
        self.metrics = metrics
        self._entries: dict[str, FieldEntry] = {}
        self._lock = threading.Lock()
        self.ready = threading.Event()
        self._bg = ThreadPoolExecutor(1, thread_name_prefix="flatserve-bg")
        #: commits of wait=false uploads, overlapped with their coordinates
        self._commits = ThreadPoolExecutor(2, thread_name_prefix="flatserve-commit")
        self._closed = False

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
    def new_field(self, spec: dict, basis):
        kw = {}
        if spec.get("roundtrip_tol") is not None:
            kw["roundtrip_tol"] = spec["roundtrip_tol"]
        return _Field()(basis, channels=spec["channels"], **kw)

    def create(self, name: str, spec: dict, basis) -> FieldEntry:
        fld = self.new_field(spec, basis)
        arrays = {"Q": np.asarray(basis.Q, np.float64), "r": np.asarray(basis.r, np.float64)}
        with self._lock:
            if name in self._entries:
                raise FieldExistsError(f"field {name!r} already exists")
            if len(self._entries) >= self.settings.max_fields:
                raise TooManyFieldsError(
                    f"this server holds {len(self._entries)} fields; the limit is "
                    f"{self.settings.max_fields}"
                )
            fid = self.storage.create_field(name, spec, arrays)
            e = FieldEntry(fid, name, spec, arrays, time.time(), field=fld, state="ready")
            self._entries[name] = e
        log.info("created field %r (k=%d, d=%d, channels=%d)", name, spec["k"], spec["d"],
                 spec["channels"])
        return e

    def delete(self, name: str) -> None:
        e = self.get(name, need_ready=False)
        with e.upload_lock, e.index_lock, e.lock.write():
            if e.deleted:
                raise FieldNotFoundError(f"no field named {name!r}")
            self.storage.delete_field(e.id)
            e.deleted = True
            with e.cond:
                e.pending.clear()
                e.pending_samples = 0
                e.cond.notify_all()
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
                e = FieldEntry(row.id, row.name, row.spec, row.basis, row.created,
                               row.snapshot_file, row.snapshot_seq)
                self._entries[row.name] = e
                entries.append((e, row))
        log.info("restoring %d stored field(s) from %s", len(entries), self.storage.data_dir)
        for e, row in entries:
            if self._closed:
                return
            self._restore(e, row)
        self.ready.set()
        log.info("ready: %d field(s) loaded", len(entries))

    def _restore(self, e: FieldEntry, row: FieldRow) -> None:
        t0 = time.perf_counter()
        try:
            basis = _Basis()(row.basis["Q"], row.basis["r"], e.k)
            fld, start = None, 0
            if row.snapshot_file:
                path = self.storage.snapshot_path(row.snapshot_file)
                try:
                    fld = _Field().load(path)
                    start = row.snapshot_seq
                    log.info("field %r: snapshot after batch %d loaded (%d samples) in %.2f s",
                             e.name, start, fld.nsamples, time.perf_counter() - t0)
                except Exception as exc:  # corrupt/missing snapshot: rebuild from batches
                    log.warning("field %r: snapshot %s unusable (%s); rebuilding from batches",
                                e.name, path, exc)
                    fld, start = None, 0
            if fld is None:
                fld = self.new_field(e.spec, basis)
            nb, nrows, _, last = self.storage.batch_stats(e.id)
            todo = sum(1 for b in self.storage.batches(e.id) if b.seq > start)
            log.info("field %r: replaying %d of %d stored batch(es)", e.name, todo, nb)
            done, tlast, replayed = 0, time.perf_counter(), 0
            for seq, form, arrays in self.storage.iter_batch_arrays(e.id, start):
                values = arrays.pop("values")
                res = apply_batch(fld, form, arrays, values)
                replayed += int(res.accepted)
                done += 1
                if time.perf_counter() - tlast > PROGRESS_EVERY_S:
                    log.info("field %r: replayed %d/%d batches (%d samples)", e.name, done, todo,
                             fld.nsamples)
                    tlast = time.perf_counter()
            with e.lock.write():
                e.field = fld
                e.last_seq = max(last, start)
                e.indexed_seq = e.last_seq
                e.snapshot_seq = start
                e.new_samples = replayed
                e.state, e.error = "ready", None
            log.info("field %r: restored, %d samples, %d batches replayed in %.2f s", e.name,
                     fld.nsamples, done, time.perf_counter() - t0)
            self._maybe_snapshot(e)
        except Exception as exc:
            log.exception("field %r: restore failed", e.name)
            e.state, e.error = "failed", str(exc)

    # -- upload -----------------------------------------------------------
    def upload(self, e: FieldEntry, form: str, arrays: dict, values: np.ndarray,
               idem_key: str | None, timings: dict | None = None, *, wait: bool = True) -> dict:
        """Durably store one batch and index it (``wait=True``) or have it indexed
        in the background (``wait=False``); see the module doc. ``timings`` (if
        given) receives the seconds spent on coordinates / inserting (``insert``
        or ``prepare``) and committing (``store``)."""
        timings = {} if timings is None else timings
        t0 = time.perf_counter()
        n = int(values.shape[0])
        stored = dict(arrays, values=values)
        chash = None
        if idem_key is not None:
            chash = content_hash(form, stored)
            timings["hash"] = time.perf_counter() - t0
        with e.upload_lock:
            self._check_writable(e)
            if idem_key is not None:
                prev = self.storage.find_batch(e.id, idem_key)
                if prev is not None:
                    if prev.content_hash != chash:
                        raise IdempotencyConflictError(
                            f"Idempotency-Key {idem_key!r} was used for a different batch"
                        )
                    return dict(self._stored_result(e, prev.seq, prev.form, prev.result),
                                replayed=True, indexed=prev.seq <= e.indexed_seq)
            if wait:
                out = self._upload_indexed(e, form, arrays, values, idem_key, chash, stored, n,
                                           timings)
            else:
                out = self._upload_deferred(e, form, arrays, values, idem_key, chash, stored, n,
                                            timings)
        if self.metrics is not None:
            self.metrics.batches.labels(e.name).inc()
            self.metrics.samples_rejected.labels(e.name).inc(len(out["rejected"]))
            if wait:
                self.metrics.samples_accepted.labels(e.name).inc(out["accepted"])
        if wait:
            self._maybe_snapshot(e)
        return out

    @staticmethod
    def _check_writable(e: FieldEntry) -> None:
        if e.deleted:
            raise FieldNotFoundError(f"no field named {e.name!r}")
        if e.state != "ready":
            raise StorageError(f"field {e.name!r} is not ready ({e.state})")

    @staticmethod
    def _response(seq: int, batch, *, duplicates, nsamples: int, indexed: bool,
                  pending: int) -> dict:
        """The response of an upload (stored with its batch for idempotent retries);
        ``batch``: an AddResult or a PreparedBatch (accepted, rejected, reasons)."""
        return {"batch": seq, "accepted": int(batch.accepted),
                "rejected": np.asarray(batch.rejected, np.int64).tolist(),
                "reasons": [str(x) for x in batch.reasons], "duplicates": duplicates,
                "nsamples": int(nsamples), "indexed": indexed, "pending_samples": pending,
                "replayed": False}

    def _stored_result(self, e: FieldEntry, seq: int, form: str, result: dict | None) -> dict:
        """The response stored for batch ``seq``; recomputed (and stored again) from
        the batch's arrays if a crash lost it (see the storage module doc)."""
        if result is not None:
            return result
        arrays = self.storage.batch_arrays(e.id, seq)
        values = arrays.pop("values")
        result = self._response(seq, prepare(e.field, form, arrays, values), duplicates=None,
                                nsamples=e.field.nsamples, indexed=seq <= e.indexed_seq,
                                pending=e.pending_samples)
        try:
            self.storage.set_result(e.id, seq, result, replace=False)
        except StorageError:  # pragma: no cover - a cache: recomputed next time
            log.warning("field %r: could not store the response of batch %d", e.name, seq)
        return result

    def batches(self, e: FieldEntry) -> list[dict]:
        """The stored batches of a field: seq, key, rows, accepted (None while the
        response is not stored: in flight, or lost in a crash), form. Reads only."""
        return [{"batch": b.seq, "idempotency_key": b.idem_key, "rows": b.nrows,
                 "accepted": None if b.result is None else int(b.result["accepted"]),
                 "form": b.form} for b in self.storage.batches(e.id)]

    @staticmethod
    def _packed(form, stored, chash):
        """``(content hash, blob)`` of a batch (hashing it if not done yet)."""
        return (content_hash(form, stored) if chash is None else chash), pack_arrays(stored)

    def _commit_batch(self, e, form, packed, idem_key, n, result_fn=None):
        """Durably store one packed batch."""
        chash, blob = packed
        return self.storage.add_batch(e.id, idem_key=idem_key, chash=chash, form=form, nrows=n,
                                      blob=blob, result_fn=result_fn)

    def _upload_indexed(self, e, form, arrays, values, idem_key, chash, stored, n, timings):
        """wait=True: insert, then commit (memory ahead of storage -> reload on failure)."""
        packed = self._packed(form, stored, chash)  # outside the locks: queries go on
        if not self.wait_indexed(e):  # commit order: every earlier batch first
            raise NotReadyError(f"field {e.name!r}: the server is shutting down")
        self._check_writable(e)
        with e.index_lock, e.lock.write():
            t1 = time.perf_counter()
            try:
                res = apply_batch(e.field, form, arrays, values)
            except InvalidInputError:
                raise  # rejected before the triangulation changed
            except BaseException as exc:
                # a failure inside the insert may leave samples in memory that were
                # never committed: reload this field from storage
                e.state, e.error = "loading", f"reloading after a failed insert: {exc}"
                self._bg.submit(self._reload, e)
                raise
            t2 = time.perf_counter()
            timings["insert"] = t2 - t1
            accepted = int(res.accepted)

            def result(seq):
                return self._response(seq, res, duplicates=int(res.duplicates),
                                      nsamples=res.nsamples, indexed=True, pending=0)

            try:
                seq, out = self._commit_batch(e, form, packed, idem_key, n, result)
            except BaseException as exc:
                # memory is ahead of storage: reload this field from storage
                if not isinstance(exc, FieldNotFoundError):
                    e.state, e.error = "loading", f"reloading after storage failure: {exc}"
                    self._bg.submit(self._reload, e)
                raise
            e.last_seq = e.indexed_seq = seq
            e.new_samples += accepted
            timings["store"] = time.perf_counter() - t2
        return out

    def _upload_deferred(self, e, form, arrays, values, idem_key, chash, stored, n, timings):
        """wait=False: validate; commit while charting; acknowledge; the indexer
        inserts later."""
        t1 = time.perf_counter()
        # bad input is refused here, before anything is stored; charting cannot fail
        # on validated input (each row gets a status)
        chart = prepare(e.field, form, arrays, values, defer=True)
        commit = self._commits.submit(
            lambda: self._commit_batch(e, form, self._packed(form, stored, chash), idem_key, n))
        try:
            prepared = chart()  # no lock: reads the basis only
        except BaseException:
            # unexpected (memory...): the client gets an error, so the batch must not
            # stay stored; nothing in memory or in any response refers to it yet
            try:
                seq, _ = commit.result()
            except BaseException:
                raise  # nothing stored, nothing changed
            try:
                self.storage.delete_batch(e.id, seq)
            except BaseException:  # still stored: memory is behind storage
                log.exception("field %r: could not remove batch %d after a failed upload; "
                              "reloading", e.name, seq)
                e.state, e.error = "loading", "reloading after a failed upload"
                if not self._closed:
                    self._bg.submit(self._reload, e)
            raise
        t2 = time.perf_counter()
        timings["prepare"] = t2 - t1
        seq, _ = commit.result()  # a storage failure propagates: nothing in memory changed
        timings["store"] = time.perf_counter() - t1  # overlaps "prepare"
        accepted = prepared.accepted
        with e.cond:
            pending = e.pending_samples + accepted
        out = self._response(seq, prepared, duplicates=None, nsamples=e.field.nsamples,
                             indexed=False, pending=pending)
        try:
            self.storage.set_result(e.id, seq, out)
        except StorageError as exc:  # the batch is durable; its response is a cache
            log.warning("field %r: could not store the response of batch %d: %s", e.name, seq, exc)
        e.last_seq = seq
        with e.cond:
            e.pending.append((seq, prepared))
            e.pending_samples += accepted
            if e.indexer is None and not self._closed:
                e.indexer = threading.Thread(target=self._index_pending, args=(e,),
                                             name=f"flatserve-index-{e.id}", daemon=True)
                e.indexer.start()
        return out

    def _index_pending(self, e: FieldEntry) -> None:
        """The field's background indexer: insert pending batches in commit order."""
        while True:
            with e.cond:
                if not e.pending or e.stop_indexing or e.state != "ready":
                    e.indexer = None
                    e.cond.notify_all()
                    return
                seq, prep = e.pending[0]
            accepted = 0
            try:
                self._before_index(e, seq)
                with e.index_lock, e.lock.write():
                    if e.deleted:
                        continue  # delete() cleared the queue
                    if seq > e.indexed_seq:  # (a reload may have replayed it already)
                        insert_prepared(e.field, prep)
                        e.indexed_seq = seq
                        e.new_samples += prep.accepted
                        accepted = prep.accepted
                    with e.cond:
                        if e.pending and e.pending[0][0] == seq:
                            e.pending.popleft()
                            e.pending_samples -= prep.accepted
                        e.cond.notify_all()
            except Exception as exc:
                # memory may hold part of the batch: rebuild the field from storage,
                # which holds every committed batch (the reload indexes them all)
                log.exception("field %r: indexing batch %d failed; reloading", e.name, seq)
                with e.cond:
                    e.state, e.error = "loading", f"reloading after indexing failure: {exc}"
                    e.pending.clear()
                    e.pending_samples = 0
                    e.indexer = None
                    e.cond.notify_all()
                if not self._closed:
                    self._bg.submit(self._reload, e)
                return
            if accepted and self.metrics is not None:
                self.metrics.samples_accepted.labels(e.name).inc(accepted)
            self._maybe_snapshot(e)

    @staticmethod
    def _before_index(e: FieldEntry, seq: int) -> None:
        """Called by the indexer before it takes the field's locks (a test hook)."""

    def wait_indexed(self, e: FieldEntry, seq: int | None = None,
                     timeout: float | None = None) -> bool:
        """Block until batch ``seq`` (default: every acknowledged batch) is indexed."""
        target = e.last_seq if seq is None else seq
        end = None if timeout is None else time.monotonic() + timeout
        with e.cond:
            while e.pending and e.pending[0][0] <= target and e.state == "ready" \
                    and not e.deleted:
                if e.indexer is None:  # stopped (shutdown): left for the replay on start
                    return False
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return False
                e.cond.wait(left)
        return True

    def _reload(self, e: FieldEntry) -> None:
        try:
            row = self.storage.field(e.id)
        except Exception as exc:
            e.state, e.error = "failed", str(exc)
            return
        with e.upload_lock, e.index_lock:
            with e.cond:
                e.pending.clear()
                e.pending_samples = 0
                e.cond.notify_all()
            self._restore(e, row)

    # -- query ------------------------------------------------------------
    def query(self, e: FieldEntry, form: str, arrays: dict, **kw):
        n = len(next(iter(arrays.values())))
        if n < SMALL_QUERY_ROWS:  # not worth starting native worker threads
            kw.setdefault("threads", 1)
        with e.lock.read():
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            res = query_batch(e.field, form, arrays, **kw)
        if self.metrics is not None:
            self.metrics.queries.labels(e.name).inc()
            self.metrics.query_rows.labels(e.name).inc(len(res.inside))
        return res

    def query_nowait(self, e: FieldEntry, form: str, arrays: dict, **kw):
        """:meth:`query` if the field's read lock is free right now, else None
        (for callers on the event loop, which must never wait for an insert)."""
        if not e.lock.try_acquire_read():
            return None
        try:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            res = query_batch(e.field, form, arrays, **kw)
        finally:
            e.lock.release_read()
        if self.metrics is not None:
            self.metrics.queries.labels(e.name).inc()
            self.metrics.query_rows.labels(e.name).inc(len(res.inside))
        return res

    # -- snapshots --------------------------------------------------------
    def _maybe_snapshot(self, e: FieldEntry) -> None:
        every = self.settings.snapshot_every
        if not every or e.new_samples < every or e.snapshot_pending or self._closed:
            return
        e.snapshot_pending = True
        try:
            self._bg.submit(self._background_snapshot, e)
        except RuntimeError:  # shut down meanwhile
            e.snapshot_pending = False

    def _background_snapshot(self, e: FieldEntry) -> None:
        try:
            self.snapshot(e)
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
        self._closed = True
        end = time.monotonic() + (DRAIN_TIMEOUT_S if drain_timeout is None else drain_timeout)
        for e in self.snapshot_entries():
            left = max(0.0, end - time.monotonic())
            if not self.wait_indexed(e, timeout=left):
                with e.cond:
                    log.warning("field %r: %d batch(es) not indexed at shutdown; they are "
                                "stored and will be replayed on start", e.name, len(e.pending))
            with e.cond:
                e.stop_indexing = True
                e.cond.notify_all()
        self._commits.shutdown(wait=True)
        self._bg.shutdown(wait=True, cancel_futures=True)
        for e in self.snapshot_entries():
            t = e.indexer
            if t is not None:  # finishing its current batch (under the field's locks)
                t.join(max(0.0, end - time.monotonic()) + 1.0)
