"""Uploads of sample batches: durable commit, idempotent retries, insert now
(``wait=true``) or in the field's background indexer (``wait=false``).

Durability (Qdrant's ``wait`` convention). In both modes the batch is validated
first (bad input is refused before anything is stored), charted while a storage
thread packs it, then committed with its response (the accepted / rejected rows
and their reasons, exact) in one transaction, and acknowledged only after the
commit:

* ``wait=true`` (default): once every earlier batch is indexed, the batch is
  committed and then inserted into the triangulation; the response is sent
  after both. A failed commit changes nothing in memory, so reads go on.
* ``wait=false``: acknowledged once committed and charted; the
  :class:`~.indexer.Indexer` inserts it later, batch by batch in commit order.
  ``indexed_seq`` is the last batch in the triangulation; snapshots only cover
  indexed batches, and a restart replays every committed batch, so nothing
  acknowledged is lost whenever the process dies.

The response of each batch is stored with it for idempotent retries (completed
durably once a ``wait=true`` batch is inserted); a retry recomputes it from the
stored arrays if it was ever lost.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from ..errors import (BacklogFullError, CostLimitError, FieldNotFoundError,
                      IdempotencyConflictError, NotReadyError, StorageError)
from ..flats import Flats
from .entry import FieldEntry, UploadResult
from .registry import Registry, stored_flats
from .blobs import content_hash, pack_arrays

log = logging.getLogger("flatserve.service")


def upload(reg: Registry, e: FieldEntry, flats: Flats, values: np.ndarray,
           idem_key: str | None, timings: dict | None = None, *, wait: bool = True) -> dict:
    """Durably store one batch and index it (``wait``) or have it indexed in the
    background; returns the response (see the module doc). ``timings`` (if
    given) receives the seconds spent on hashing (``hash``), coordinates
    (``prepare``), the insert (``insert``) and the commit (``store``)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    stored = dict(flats.arrays, values=values)
    chash = None
    if idem_key is not None:
        chash = content_hash(flats.form, stored)
        timings["hash"] = time.perf_counter() - t0
    with e.upload_lock:
        e.check_writable()
        if idem_key is not None:
            prev = reg.storage.find_batch(e.id, idem_key)
            if prev is not None:
                if prev.content_hash != chash:
                    raise IdempotencyConflictError(
                        f"Idempotency-Key {idem_key!r} was used for a different batch")
                if wait:  # a retry with wait=true answers once its batch is visible
                    reg.wait_indexed(e, prev.seq)
                return dict(_stored_result(reg, e, prev.seq, prev.form, prev.result),
                            replayed=True, indexed=prev.seq <= e.indexed_seq)
        pending = e.indexer.counts()[1]
        _check_cost(reg, e, flats, pending)
        if not wait and pending + len(flats) > reg.settings.max_pending_samples:
            raise BacklogFullError(
                f"field {e.name!r}: {pending} acknowledged samples wait for their insert; "
                f"{len(flats)} more would pass the limit of {reg.settings.max_pending_samples} "
                "(FLATSERVE_MAX_PENDING_SAMPLES): retry later, or upload with wait=true")
        if wait and not reg.wait_indexed(e):  # commit order: every earlier batch first
            raise NotReadyError(f"field {e.name!r}: the server is shutting down")
        e.check_writable()
        seq, prepared, out = _commit_and_chart(reg, e, flats, values, idem_key, chash, stored,
                                               timings, wait=wait)
        if wait:
            out = _insert_now(reg, e, seq, prepared, timings)
            _store_result(reg, e, seq, out)
        e.last_seq = seq
        if not wait:
            e.indexer.enqueue(seq, prepared, lambda s, b: reg.index(e, s, b), str(e.id))
    if reg.metrics is not None:
        reg.metrics.batches.labels(e.name).inc()
        reg.metrics.samples_rejected.labels(e.name).inc(len(out["rejected"]))
        if wait:
            reg.metrics.samples_accepted.labels(e.name).inc(out["accepted"])
    if wait:
        reg.maybe_snapshot(e)
    return out


#: Cells of a Delaunay triangulation per sample by dimension D (uniform points,
#: measured with flatserve.Triangulation: 5,000 points for D <= 3, 200 for D = 8);
#: the estimate of a field with fewer than COST_MIN_SAMPLES samples.
CELLS_PER_SAMPLE = {2: 2.0, 3: 6.6, 4: 28.0, 5: 129.0, 6: 512.0, 7: 1704.0, 8: 5195.0}
COST_MIN_SAMPLES = 1000


def _check_cost(reg, e: FieldEntry, flats: Flats, pending: int) -> None:
    """Refuse (413) an upload expected to make the field's triangulations larger than
    ``max_simplices`` cells in all: the field's own cells per stored sample once it
    has some, else :data:`CELLS_PER_SAMPLE` (high-dimensional fields grow very fast:
    200 samples in D = 8 make a million cells). An atlas field stores a sample once
    in every chart whose domain holds it: the batch's rows are counted per chart
    (``Atlas.held``), and the ``pending`` samples with the batch's duplication."""
    f = e.field
    D, n = f.ndim, len(flats)
    if e.spec.is_atlas:
        stored = f.nstored
        copies = float(f.atlas.held(flats, f.atlas.reach).sum()) / n
    else:
        stored, copies = f.nsamples, 1.0
    per = f.nsimplex / stored if stored >= COST_MIN_SAMPLES else CELLS_PER_SAMPLE.get(
        D, CELLS_PER_SAMPLE[8] * 3.0 ** (D - 8))
    total = stored + (pending + n) * copies
    expected = total * per
    limit = reg.settings.max_simplices
    if expected > limit:
        held = f" (x {copies:.2f} charts holding each)" if e.spec.is_atlas else ""
        raise CostLimitError(
            f"field {e.name!r}: about {expected:,.0f} cells expected after this upload "
            f"({total:,.0f} stored samples: {stored} + {pending + n} new{held}; x {per:,.0f} "
            f"cells per sample in dimension {D}); the limit is {limit:,} "
            "(FLATSERVE_MAX_SIMPLICES)")


def _commit_and_chart(reg, e, flats, values, idem_key, chash, stored, timings, *,
                      wait: bool):
    """Validate the batch, chart it while a storage thread packs (and hashes) it,
    then commit it together with its first response in one transaction: every
    stored batch is listed with its accepted / rejected rows, whenever the process
    dies. Returns ``(seq, PreparedBatch, response)``; on failure nothing is stored."""
    t1 = time.perf_counter()
    # bad input is refused here, before anything is stored; charting cannot fail
    # on validated input (each row gets a status)
    chart = e.field.prepare(flats, values, defer=True)
    packing = reg.commit_pool.submit(
        lambda: (content_hash(flats.form, stored) if chash is None else chash,
                 pack_arrays(stored)))
    prepared = chart()  # no lock: reads the basis only
    timings["prepare"] = time.perf_counter() - t1
    h, blob = packing.result()
    pending = 0 if wait else e.indexer.counts()[1] + prepared.accepted

    def response(seq: int) -> dict:
        return UploadResult.of(seq, prepared, nsamples=e.field.nsamples, indexed=False,
                               pending=pending).to_dict()

    seq = reg.storage.add_batch(e.id, idem_key=idem_key, chash=h, form=flats.form,
                                nrows=len(flats), blob=blob, result_fn=response)
    timings["store"] = time.perf_counter() - t1 - timings["prepare"]
    return seq, prepared, response(seq)


def _insert_now(reg, e, seq, prepared, timings) -> dict:
    """wait=true: insert a committed batch (storage is ahead of memory until then)."""
    t2 = time.perf_counter()
    with e.index_lock:
        if e.deleted:
            raise FieldNotFoundError(f"no field named {e.name!r}")
        try:
            res = e.field.insert_prepared(prepared)
        except Exception as exc:
            # the batch is committed but maybe half in memory: rebuild from storage,
            # which indexes it; the client is told so (a 503, not a 500: nothing is lost)
            reg.reload(e, f"reloading after a failed insert: {exc}")
            raise NotReadyError(
                f"field {e.name!r}: batch {seq} is stored, but inserting it failed ({exc}); "
                "the field is being rebuilt from storage, which indexes it: retry with the "
                "same Idempotency-Key for its response") from exc
        except BaseException as exc:
            reg.reload(e, f"reloading after a failed insert: {exc}")
            raise
        e.indexed_seq = seq
        e.new_samples += res.accepted
    timings["insert"] = time.perf_counter() - t2
    return UploadResult.of(seq, res, nsamples=res.nsamples, indexed=True, pending=0).to_dict()


def _store_result(reg, e, seq, out) -> None:
    """Store the complete response of an indexed batch (wait=true), durably, before
    the acknowledgement."""
    try:
        reg.storage.set_result(e.id, seq, out, durable=True)
    except StorageError as exc:  # the batch is durable; its response is a cache
        log.warning("field %r: could not store the response of batch %d: %s", e.name, seq, exc)


def _stored_result(reg, e: FieldEntry, seq: int, form: str, result: dict | None) -> dict:
    """The response stored for batch ``seq``; recomputed (and stored again) from
    the batch's arrays if a crash lost it (see the storage module doc)."""
    if result is not None:
        return result
    arrays = reg.storage.batch_arrays(e.id, seq)
    values = arrays.pop("values")
    prepared = e.field.prepare(stored_flats(e, form, arrays), values)
    result = UploadResult.of(seq, prepared, nsamples=e.field.nsamples,
                             indexed=seq <= e.indexed_seq,
                             pending=e.indexer.counts()[1]).to_dict()
    try:
        reg.storage.set_result(e.id, seq, result, replace=False)
    except StorageError:  # pragma: no cover - a cache: recomputed next time
        log.warning("field %r: could not store the response of batch %d", e.name, seq)
    return result


def batches(reg: Registry, e: FieldEntry) -> list[dict]:
    """The stored batches of a field: seq, key, rows, accepted (None while the
    response is not stored: in flight, or lost in a crash), form. Reads only."""
    return [{"batch": b.seq, "idempotency_key": b.idem_key, "rows": b.nrows,
             "accepted": None if b.result is None else int(b.result["accepted"]),
             "form": b.form} for b in reg.storage.batches(e.id)]
