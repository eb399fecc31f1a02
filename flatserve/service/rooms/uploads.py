"""Uploads of sample batches: durable commit, idempotent retries, applied by the
log follower (``wait=true``: before the response; ``wait=false``: after it).

Durability (Qdrant's ``wait`` convention). In both modes the batch is validated
first (bad input is refused before anything is stored), charted while a storage
thread packs it, then committed with its response (the accepted / rejected rows
and their reasons, exact) and its log entry in one transaction, and
acknowledged only after the commit. The charted batch is handed to this
replica's log follower (:mod:`.replica`), which inserts it in log order, as it
inserts every other replica's batches:

* ``wait=true`` (default): the response is sent once this replica has applied
  the batch (it is visible to queries here; ``duplicates`` and ``nsamples`` are
  known). A failed commit changes nothing in memory, so reads go on.
* ``wait=false``: acknowledged once committed and charted (``indexed: false``);
  at most ``max_pending_samples`` samples of a field may wait (429).

Every response carries the batch's log ``position``: a read that passes it as
``min_position`` (on any replica) sees the batch. The response of each batch is
stored with it for idempotent retries (completed durably once a ``wait=true``
batch is applied); the key is unique per field in the database, so a retry on
another replica finds it too, and a retry racing the first attempt gets its
response. A retry recomputes the response from the stored arrays if a crash
lost it.
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ...atlas_field import choose_unit
from ...contract import SampledField
from ...field import AddResult, PreparedBatch
from ...flats import Flats
from .applier import stored_flats
from ..log.backend import LogBackend
from ..log.rows import BatchRow, KeyTakenError
from ..log.blobs import UNIT_ARRAY, content_hash, pack_arrays, split_batch
from .costs import COST_MIN_SAMPLES, cells_per_sample
from .entry import FieldEntry
from .replica import Follower
from ..reports import BatchInfo, UploadResult
from ..settings import Settings
from ..status import (BacklogFullError, CostLimitError, CostPendingError, FieldNotFoundError,
                     IdempotencyConflictError, NotReadyError, StorageError)

log = logging.getLogger("flatserve.service")


def upload_result(seq: int, res: AddResult | PreparedBatch, *, nsamples: int, indexed: bool,
                  pending: int, position: int) -> UploadResult:
    """The response to an upload, from an :class:`AddResult` (indexed: duplicates
    known) or a :class:`PreparedBatch` (not yet indexed: duplicates null)."""
    return UploadResult(
        batch=seq, accepted=int(res.accepted),
        rejected=np.asarray(res.rejected, np.int64).tolist(),
        reasons=[str(x) for x in res.reasons],
        duplicates=int(res.duplicates) if isinstance(res, AddResult) else None,
        nsamples=int(nsamples), indexed=indexed, pending_samples=int(pending),
        replayed=False, position=int(position))


def check_cost(name: str, field: SampledField, size: tuple[int, int], pending: int,
               rows: int, copies: float, max_simplices: int, *,
               what: str = "this upload") -> None:
    """Refuse new rows expected to make a field's triangulations larger than
    ``max_simplices`` cells in all: the cost guard of an upload (one batch) and of
    an import (all its batches at once, before the first is stored).

    The estimate is the field's size when it last held its batches whole (``size``:
    :attr:`.entry.FieldEntry.complete_size`, set by :meth:`.entry.FieldEntry.mark_indexed`;
    never a triangulation with a batch half inserted, whose cells per sample are far
    from the final ones) plus the ``pending`` samples and the new ``rows``, times the
    cells per sample measured then (:func:`.costs.cells_per_sample` below
    :data:`.costs.COST_MIN_SAMPLES` samples; high-dimensional fields grow very fast:
    200 samples in D = 8 make a million cells). A field of several shards stores a
    sample once in every shard that holds it: the new rows are counted with their
    ``copies`` (the field's ``copies`` of them: the mean over the rows).

    Parameters
    ----------
    name : str
        The field's name (for the message).
    field : SampledField
        The field, or an empty one of its definition (a field not created yet).
    size : tuple of int
        ``(samples, cells)`` when it last held its batches whole; ``(0, 0)`` for a
        new field.
    pending : int
        Its samples acknowledged and not yet indexed.
    rows, copies : int, float
        The new rows and the charts holding each on average.
    max_simplices : int
    what : str
        What brings the rows, for the message.

    Raises
    ------
    CostLimitError
        413: the rows cannot pass, now or later (the field holds too much already
        with them, or they alone are too many).
    CostPendingError
        429 with ``Retry-After``: they would pass but for the ``pending`` samples
        (acknowledged, not yet indexed): once they are in, the field is measured
        again and duplicates among them drop out.
    """
    D = field.ndim
    stored, cells = size
    per = cells / stored if stored >= COST_MIN_SAMPLES else cells_per_sample(D)
    total = stored + (pending + rows) * copies
    expected = total * per
    if expected <= max_simplices:
        return
    held = f" (x {copies:.2f} charts holding each)" if len(field.shards) > 1 else ""
    msg = (f"field {name!r}: about {expected:,.0f} cells expected after {what} "
           f"({total:,.0f} stored samples: {stored} + {pending + rows} new{held}; x "
           f"{per:,.0f} cells per sample in dimension {D}); the limit is {max_simplices:,} "
           "(FLATSERVE_MAX_SIMPLICES)")
    if pending and (stored + rows * copies) * per <= max_simplices:
        raise CostPendingError(f"{msg}, counting {pending} acknowledged samples not yet "
                               "indexed: retry once they are (the field is measured again)")
    raise CostLimitError(msg)


class UploadService:
    """Uploads of sample batches (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``max_pending_samples``, ``max_simplices``, ``apply_wait_timeout``.
    storage : LogBackend
    follower : Follower
        Takes the charted batches (hand-over) and tells when they are applied.
    metrics : Metrics, optional
    """

    def __init__(self, settings: Settings, storage: LogBackend, follower: Follower,
                 metrics=None) -> None:
        self.settings = settings
        self.storage = storage
        self.follower = follower
        self.metrics = metrics
        #: commits of uploads, overlapped with their coordinates
        self._commits = ThreadPoolExecutor(2, thread_name_prefix="flatserve-commit")

    def close(self) -> None:
        self._commits.shutdown(wait=True)

    # -- the upload ---------------------------------------------------------------------------
    def upload(self, e: FieldEntry, flats: Flats, values: np.ndarray, idem_key: str | None,
               timings: dict | None = None, *, wait: bool = True,
               cost_checked: bool = False) -> UploadResult:
        """Durably store one batch and have it applied (see the module doc); returns
        the response. ``timings`` (if given) receives the seconds spent on hashing
        (``hash``), coordinates (``prepare``), the commit (``store``) and, with
        ``wait``, the wait for the insert (``insert``). The batch is held to
        ``max_simplices`` (:func:`check_cost`) unless ``cost_checked``: an import
        checks the cost of all its batches at once, before it stores the first
        (:mod:`.transfer`), so that it is refused whole or stored whole."""
        timings = {} if timings is None else timings
        t0 = time.perf_counter()
        stored = dict(flats.arrays, values=values)
        chash = None
        if idem_key is not None:
            chash = content_hash(flats.form, stored)
            timings["hash"] = time.perf_counter() - t0
        with e.upload_lock:
            e.check_writable()
            prev = self.storage.find_batch(e.id, idem_key) if idem_key is not None else None
            if prev is None:
                pending = e.pending_counts()[1]
                if not cost_checked:  # (an import's rows not stored yet count as pending)
                    check_cost(e.name, e.field, e.complete_size, pending + e.reserved,
                               len(flats), e.field.copies(flats), self.settings.max_simplices)
                if not wait and pending + len(flats) > self.settings.max_pending_samples:
                    raise BacklogFullError(
                        f"field {e.name!r}: {pending} acknowledged samples wait for their "
                        f"insert; {len(flats)} more would pass the limit of "
                        f"{self.settings.max_pending_samples} (FLATSERVE_MAX_PENDING_SAMPLES): "
                        "retry later, or upload with wait=true")
                e.check_writable()
                try:
                    seq, pos, out = self._commit_and_chart(e, flats, values, idem_key, chash,
                                                           stored, timings, wait=wait)
                except KeyTakenError as exc:  # stored meanwhile through another replica
                    prev = exc.existing
        if prev is not None:
            return self._replay(e, prev, chash, idem_key, wait)
        if wait:
            out = self._await_insert(e, seq, pos, timings)
            self._store_result(e, seq, out)
        if self.metrics is not None:
            self.metrics.batches.labels(e.name).inc()
            self.metrics.samples_rejected.labels(e.name).inc(len(out.rejected))
        return out

    def _replay(self, e: FieldEntry, prev: BatchRow, chash: str | None, idem_key: str,
                wait: bool) -> UploadResult:
        """The response to a retry of a stored batch (``wait``: once applied here)."""
        if prev.content_hash != chash:
            raise IdempotencyConflictError(
                f"Idempotency-Key {idem_key!r} was used for a different batch")
        more = {}
        if wait:  # a retry with wait=true answers once its batch is visible
            deadline = self._await_here(e, prev.seq, prev.position)
            counts = self._applied_everywhere(e, prev.position, deadline)
            # a complete response (of a wait=true upload) keeps the counts it was answered
            # with; one acknowledged before its insert (wait=false) has them filled in
            if not (prev.result is not None and prev.result.get("indexed")):
                more = counts
        return self._stored_result(e, prev.seq, prev.form, prev.result).model_copy(
            update={"replayed": True, "indexed": prev.seq <= e.indexed_seq,
                    "position": prev.position, **more})

    def _commit_and_chart(self, e, flats, values, idem_key, chash, stored, timings, *,
                          wait: bool) -> tuple[int, int, UploadResult]:
        """Validate the batch, chart it while a storage thread packs (and hashes) it,
        then commit it together with its first response and its log entry in one
        transaction: every stored batch is listed with its accepted / rejected rows,
        whenever the process dies. The charted batch is handed to the follower inside
        the commit. Returns ``(seq, position, response)``; on failure nothing is
        stored."""
        t1 = time.perf_counter()
        # bad input is refused here, before anything is stored; charting cannot fail
        # on validated input (each row gets a status)
        # a field whose unit of length comes from the data and that has inserted no batch
        # here yet: this batch is charted in its own unit (choose_unit of its rows), which
        # is stored with it; the batch first in the log sets the field's unit everywhere
        # (units.adopt_unit; a batch charted here in another unit is charted again
        # when applied). The field itself is not changed here.
        record = {}
        target = e.field
        if e.field.unit_from_data:
            e.field.prepare(flats, values, defer=True)  # validates (raises) first
            unit = choose_unit(e.field.atlas, flats, values)  # (a fit: seconds, a thread)
            target, record = e.field.in_unit(unit), {UNIT_ARRAY: np.array([unit])}
        chart = target.prepare(flats, values, defer=True)
        packing = self._commits.submit(
            lambda: (content_hash(flats.form, stored) if chash is None else chash,
                     pack_arrays({**stored, **record})))
        prepared = chart()  # no lock: reads the basis only
        timings["prepare"] = time.perf_counter() - t1
        h, blob = packing.result()
        pending = e.pending_counts()[1] + prepared.accepted
        handed: list[int] = []

        def response(seq: int, position: int) -> UploadResult:
            return upload_result(seq, prepared, nsamples=e.field.nsamples, indexed=False,
                                 pending=pending, position=position)

        def first_response(seq: int, position: int) -> dict:
            # inside the transaction: the follower finds the charted batch when it reads
            # the entry (taken back below if the commit fails)
            self.follower.hand_over(position, e.id, seq, prepared, want_result=wait)
            handed.append(position)
            e.add_pending(position, prepared.accepted)
            return response(seq, position).model_dump()

        try:
            seq, pos = self.storage.add_batch(e.id, idem_key=idem_key, chash=h,
                                              form=flats.form, nrows=len(flats), blob=blob,
                                              result_fn=first_response)
        except BaseException:
            for p in handed:
                self.follower.take_back(p)
                e.drop_pending(p)
            raise
        timings["store"] = time.perf_counter() - t1 - timings["prepare"]
        return seq, pos, response(seq, pos)

    def _await_insert(self, e: FieldEntry, seq: int, pos: int, timings: dict) -> UploadResult:
        """wait=true: wait until the follower has inserted the committed batch here."""
        t2 = time.perf_counter()
        deadline = self._await_here(e, seq, pos)
        res, failed = self.follower.take_result(pos)
        if failed is not None:
            # the batch is committed but its insert failed: the follower rebuilt the field
            # from storage, which indexes it; the client is told so (a 503, not a 500)
            raise NotReadyError(
                f"field {e.name!r}: batch {seq} is stored, but inserting it failed ({failed}); "
                "the field is being rebuilt from storage, which indexes it: retry with the "
                "same Idempotency-Key for its response")
        if res is None and e.deleted:
            raise FieldNotFoundError(f"no field named {e.name!r} (deleted after batch {seq} "
                                     "was stored)")
        if res is None:  # not inserted here: the field was marked failed (or is being rebuilt)
            raise NotReadyError(
                f"field {e.name!r}: batch {seq} is stored, but the field is not indexed on "
                f"this replica now ({e.state}: {e.error}); it is restored from storage, which "
                "indexes it: retry with the same Idempotency-Key for its response")
        counts = self._applied_everywhere(e, pos, deadline)
        timings["insert"] = time.perf_counter() - t2
        return upload_result(seq, res, nsamples=res.nsamples, indexed=True, pending=0,
                             position=pos).model_copy(update=counts)

    def _await_here(self, e: FieldEntry, seq: int, pos: int) -> float:
        """wait=true: wait until batch ``seq`` (at log ``pos``) is applied here, up to
        ``apply_wait_timeout`` (NotReadyError, 503, past it); returns the end of that
        timeout (:func:`time.monotonic`), which the wait for the field's shards
        (:meth:`_applied_everywhere`) does not pass: one timeout for the request."""
        deadline = time.monotonic() + self.settings.apply_wait_timeout
        self.follower.await_applied(pos, f"batch {seq} of {e.name!r}",
                                    self.settings.apply_wait_timeout)
        return deadline

    def _applied_everywhere(self, e: FieldEntry, pos: int, deadline: float) -> dict:
        """wait=true: once the batch at ``pos`` is applied where the field's shards live
        (cluster mode: every shard group asked, until ``deadline`` on
        :func:`time.monotonic`, the end of the request's ``apply_wait_timeout`` begun
        by the wait here; ShardUnavailableError, 503, if one is not there by then), the
        response's ``nsamples`` and ``duplicates`` counted there; {} when this process
        holds the field (its insert counted them)."""
        return e.field.applied_counts(pos, max(0.0, deadline - time.monotonic()))

    def _store_result(self, e: FieldEntry, seq: int, out: UploadResult) -> None:
        """Store the complete response of an indexed batch (wait=true), durably, before
        the acknowledgement."""
        try:
            self.storage.set_result(e.id, seq, out.model_dump(), durable=True)
        except StorageError as exc:  # the batch is durable; its response is a cache
            log.warning("field %r: could not store the response of batch %d: %s", e.name,
                        seq, exc)

    def _stored_result(self, e: FieldEntry, seq: int, form: str, result: dict | None
                       ) -> UploadResult:
        """The response stored for batch ``seq``; recomputed (and stored again) from
        the batch's arrays if a crash lost it (see the storage module doc)."""
        if result is not None:
            return UploadResult.model_validate(result)
        arrays, values, _ = split_batch(self.storage.batch_arrays(e.id, seq))
        prepared = e.field.prepare(stored_flats(e, form, arrays), values)
        row = next((b for b in self.storage.batches(e.id, after_seq=seq - 1) if b.seq == seq),
                   None)
        out = upload_result(seq, prepared, nsamples=e.field.nsamples,
                            indexed=seq <= e.indexed_seq, pending=e.pending_counts()[1],
                            position=row.position if row is not None else 0)
        try:
            self.storage.set_result(e.id, seq, out.model_dump(), replace=False)
        except StorageError:  # pragma: no cover - a cache: recomputed next time
            log.warning("field %r: could not store the response of batch %d", e.name, seq)
        return out

    def batches(self, e: FieldEntry) -> list[BatchInfo]:
        """The stored batches of a field: seq, key, rows, accepted (None while the
        response is not stored: in flight, or lost in a crash), form. Reads only."""
        return [BatchInfo(batch=b.seq, idempotency_key=b.idem_key, rows=b.nrows,
                          accepted=None if b.result is None else int(b.result["accepted"]),
                          form=b.form) for b in self.storage.batches(e.id)]
