"""The fields a server holds: in-memory :class:`flatserve.Field` objects, their
locks, durable storage, restore on start and background snapshots.

Concurrency per field
---------------------
* ``lock`` (readers/writer): queries read, inserts write, so a query never sees
  a half-inserted batch;
* ``upload_lock``: serialises uploads (and snapshots, which must see a field
  that no upload changes) without blocking queries.

Durability of an upload: the batch is applied to the in-memory field and its
arrays are committed to SQLite under the write lock; the response is sent only
after the commit. If the commit fails the field is reloaded from storage.
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field as dc_field

import numpy as np

from ..errors import FieldExistsError, FieldNotFoundError, StorageError
from .errors import IdempotencyConflictError, NotReadyError, TooManyFieldsError
from .rwlock import RWLock
from .settings import Settings
from .storage import FieldRow, Storage, content_hash, pack_arrays

log = logging.getLogger("flatserve.service")

PROGRESS_EVERY_S = 2.0
#: queries with fewer rows run on one native thread (the request is the unit of parallelism)
SMALL_QUERY_ROWS = 2048


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
        with e.upload_lock, e.lock.write():
            if e.deleted:
                raise FieldNotFoundError(f"no field named {name!r}")
            self.storage.delete_field(e.id)
            e.deleted = True
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
               idem_key: str | None, timings: dict | None = None) -> dict:
        """Insert and durably store one batch; ``timings`` (if given) receives the
        seconds spent inserting (``insert``) and committing (``store``)."""
        timings = {} if timings is None else timings
        t0 = time.perf_counter()
        stored = dict(arrays, values=values)
        chash = content_hash(form, stored)
        blob = pack_arrays(stored)
        n = int(values.shape[0])
        with e.upload_lock:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            if e.state != "ready":
                raise StorageError(f"field {e.name!r} is not ready ({e.state})")
            if idem_key is not None:
                prev = self.storage.find_batch(e.id, idem_key)
                if prev is not None:
                    if prev.content_hash != chash:
                        raise IdempotencyConflictError(
                            f"Idempotency-Key {idem_key!r} was used for a different batch"
                        )
                    return dict(prev.result, replayed=True)
            with e.lock.write():
                t1 = time.perf_counter()
                res = apply_batch(e.field, form, arrays, values)
                t2 = time.perf_counter()
                timings["insert"] = t2 - t1
                rejected = np.asarray(res.rejected, np.int64).tolist()
                accepted = int(res.accepted)

                def result(seq):
                    return {"batch": seq, "accepted": accepted, "rejected": rejected,
                            "reasons": [str(x) for x in res.reasons],
                            "duplicates": int(res.duplicates), "nsamples": int(res.nsamples),
                            "replayed": False}

                try:
                    seq, out = self.storage.add_batch(
                        e.id, idem_key=idem_key, chash=chash, form=form, nrows=n, blob=blob,
                        result_fn=result)
                except BaseException as exc:
                    # memory is ahead of storage: reload this field from storage
                    if not isinstance(exc, FieldNotFoundError):
                        e.state, e.error = "loading", f"reloading after storage failure: {exc}"
                        self._bg.submit(self._reload, e)
                    raise
                e.last_seq = seq
                e.new_samples += accepted
                timings["store"] = time.perf_counter() - t2 + (t1 - t0)
        if self.metrics is not None:
            self.metrics.samples_accepted.labels(e.name).inc(accepted)
            self.metrics.samples_rejected.labels(e.name).inc(len(rejected))
            self.metrics.batches.labels(e.name).inc()
        self._maybe_snapshot(e)
        return out

    def _reload(self, e: FieldEntry) -> None:
        try:
            row = self.storage.field(e.id)
        except Exception as exc:
            e.state, e.error = "failed", str(exc)
            return
        with e.upload_lock:
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

    # -- snapshots --------------------------------------------------------
    def _maybe_snapshot(self, e: FieldEntry) -> None:
        every = self.settings.snapshot_every
        if not every or e.new_samples < every or e.snapshot_pending or self._closed:
            return
        e.snapshot_pending = True
        self._bg.submit(self._background_snapshot, e)

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
        with e.upload_lock:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {e.name!r}")
            if e.state != "ready":
                raise StorageError(f"field {e.name!r} is not ready ({e.state})")
            seq = e.last_seq
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

    def close(self) -> None:
        self._closed = True
        self._bg.shutdown(wait=True, cancel_futures=True)
