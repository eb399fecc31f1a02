"""One shard group of one field, in a process of its own: restore, follow the log, answer.

A :class:`ShardWorker` holds some charts of one field (``charts``; a one-chart
field's one shard is chart 0). It needs no front:

1. **Restore**: the field's newest snapshot, its own charts' parts only
   (:func:`flatserve.contract.load_field` with ``only``), else an empty field;
   the snapshot's log position is where it starts.
2. **Follow**: it reads the shared log after that position, in order, and for
   each ``batch`` entry of its field reads the batch, routes and charts the
   rows of its own charts (``prepare(..., only=charts)``) and inserts them in
   slices of ``insert_slice_rows``: exactly the calls the one-process field
   makes on those charts, so a chart here holds the same bits as the same
   chart of a field that applied the whole log (tested). A ``delete`` of its
   field ends it.
3. **Answer**: :meth:`ShardWorker.query` (its charts' answers on the rows a
   front routed to them, once it has applied the log position the front asks
   for), :meth:`ShardWorker.parts` (its charts' snapshot parts at one log
   position: a front assembles the field's snapshot from every group's), and
   :meth:`ShardWorker.status` (now, or once it has applied a log position:
   :meth:`ShardWorker.applied`).

Where a worker lives (a Ray actor, :mod:`.ray_shards`; a thread in tests) is
not this module's business.
"""
from __future__ import annotations

import io
import logging
import os
import tempfile
import threading
import time
from collections import OrderedDict

from ...contract import load_field, part_key
from ...tiles import TileHost, hosting
from ..applier import RESTORE_RETRY_S, entry_of, read_batch, until_reachable
from ..backend import LogBackend, SnapshotGoneError, open_backend
from ..catalogue import FieldState
from ..entry import FieldSpec
from ..replica import IDLE_WAIT_S, READ_CHUNK
from ..status import (FieldNotFoundError, NotReadyError, ShardUnavailableError, StorageError,
                      StorageUnavailableError)
from ..units import adopt_unit

log = logging.getLogger("flatserve.service.shard")

#: batches whose duplicates a worker remembers (the latest applied; an upload with
#: ``wait=true`` asks for its own at once)
KEEP_DUPLICATES = 256


class ShardAheadError(NotReadyError):
    """A snapshot asked a shard for its charts at a log position it has passed
    (the field's other shards are behind it): the snapshot is tried again later."""


def rss_bytes() -> int:
    """Resident memory of this process (``/proc/self/status``; 0 where unknown)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return 0


class ShardWorker:
    """Some charts of one field, following the log (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``database_url`` (the shared log; unset: the SQLite database of ``data_dir``,
        read as a follower), ``insert_slice_rows`` (the same as the
        fronts': the slices of an insert decide the bits of a chart).
    field_id : int
    charts : sequence of int
        The charts this worker holds.
    storage : LogBackend, optional
        Default: :func:`~flatserve.service.backend.open_backend` of ``settings``, a
        follower (it never writes the log).
    tile_host : TileHost, optional
        Where a tiled field's tiles live (:func:`flatserve.tiles.hosting`; in a Ray
        actor: :class:`~.tiles.RayTileHost`, each tile in an actor of its own);
        default: this process.
    start : bool
        Start restoring and following at once (default).
    """

    def __init__(self, settings, field_id: int, charts, *, storage: LogBackend | None = None,
                 tile_host: TileHost | None = None, start: bool = True) -> None:
        self.settings = settings
        self.field_id = int(field_id)
        self.charts = tuple(sorted(int(c) for c in charts))
        self.only = frozenset(self.charts)
        self._storage = storage
        self.tile_host = tile_host or TileHost()
        self.field = None
        self.spec: FieldSpec | None = None
        #: every log entry up to this position is applied
        self.through = 0
        #: the field's last batch applied: its seq and log position
        self.seq = 0
        self.position = 0
        #: ``LOADING`` (restoring), ``READY`` (following the log, answering) or
        #: ``FAILED`` (``error`` says why: a defect, or the field was deleted)
        self.state = FieldState.LOADING
        #: the field's cells after the last batch applied (counted then: a tiled
        #: field counts its tiles' cells under its lock, which an insert holds)
        self.cells = 0
        self.error: str | None = None
        self.restored_from: str | None = None
        #: per log position of a batch applied here (the latest :data:`KEEP_DUPLICATES`),
        #: the rows of its charts' own that coincided with a sample already held
        self._duplicates: OrderedDict[int, int] = OrderedDict()
        self._cond = threading.Condition()
        self._hold: int | None = None
        #: one snapshot's parts at a time: each holds the worker at its own position
        #: and counts the bytes its tiles stored
        self._parts_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="flatserve-shard", daemon=True)
        if start:
            self.start()

    @property
    def storage(self) -> LogBackend:
        if self._storage is None:
            self._storage = open_backend(self.settings, follower=True)
        return self._storage

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop following (between two batches) and close the storage."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._storage is not None:
            self._storage.wake()
        if self._thread.is_alive():
            self._thread.join(timeout)
        if self._storage is not None:
            self._storage.close()

    # -- restore and follow ---------------------------------------------------------------
    def _run(self) -> None:
        what = f"shard {self.charts} of field {self.field_id}"
        try:  # the database unreachable: tried again (queries wait)
            until_reachable(self._restore, self._stop.is_set, self._stop.wait,
                            f"{what}: restore", errors=(StorageError,),
                            on_retry=lambda exc: self._set_state(FieldState.LOADING, str(exc)))
        except FieldNotFoundError:
            self._set_state(FieldState.FAILED, "the field was deleted")
            return
        except StorageError:  # (stopping)
            return
        except Exception as exc:  # a defect: say so, never answer from a half field
            log.exception("%s: restore failed", what)
            self._set_state(FieldState.FAILED, f"restore failed: {exc}")
            return
        self._set_state(FieldState.READY, None)
        while not self._stop.is_set():
            try:
                if not self._follow_once():
                    self.storage.wait_for_change(IDLE_WAIT_S)
            except FieldNotFoundError:
                self._set_state(FieldState.FAILED, "the field was deleted")
                return
            except StorageError as exc:  # the log unreachable: try again (queries wait)
                log.warning("%s: following the log: %s", what, exc)
                self._stop.wait(RESTORE_RETRY_S)
            except Exception as exc:
                log.exception("%s: applying the log failed", what)
                self._set_state(FieldState.FAILED, f"applying the log failed: {exc}")
                return

    def _set_state(self, state: FieldState, error: str | None) -> None:
        with self._cond:
            self.state, self.error = state, error
            self._cond.notify_all()

    def _restore(self) -> None:
        t0 = time.perf_counter()
        for _ in range(5):
            row = self.storage.field(self.field_id)
            # checked as a create's (a definition no create makes fails this worker
            # with a named error, never a crash Ray would restart again and again)
            e = entry_of(row)
            spec = e.spec
            fld = None
            if row.snapshot_file:
                try:
                    with hosting(self.tile_host):
                        fld = self.storage.load_snapshot(
                            row, lambda path, parts: load_field(path, parts, only=self.only))
                except SnapshotGoneError:
                    continue  # replaced meanwhile: take the new one
                except StorageError:
                    raise
                except Exception as exc:  # damaged: the log has every batch
                    if getattr(self.tile_host, "lost", None):  # a tile lost, not the snapshot
                        raise
                    log.warning("shard %s of field %d: snapshot unusable (%s); replaying the "
                                "log", self.charts, self.field_id, exc)
                    fld = None
                if fld is not None and getattr(fld, "own_samples", ()) is None:
                    fld = None  # an older snapshot without its charts' own samples
            break
        else:
            raise StorageUnavailableError("the field's snapshot kept being replaced")
        if fld is None:
            with hosting(self.tile_host):
                fld = spec.new_field(e.basis)
            start, seq = row.position, 0
            self.restored_from = "the log"
        else:
            start, seq = row.snapshot_position, row.snapshot_seq
            self.restored_from = f"snapshot after batch {seq}"
        cells = int(fld.nsimplex)
        with self._cond:
            self.spec, self.field, self.cells = spec, fld, cells
            self.through, self.seq, self.position = start, seq, start if seq else 0
            self._cond.notify_all()
        log.info("shard %s of field %d: restored from %s in %.2f s", self.charts,
                 self.field_id, self.restored_from, time.perf_counter() - t0)

    def _follow_once(self) -> bool:
        """Apply the next entries of the log; False if there were none."""
        entries = self.storage.read_log(self.through, READ_CHUNK)
        for en in entries:
            if self._stop.is_set():
                return True
            if en.field_id == self.field_id:
                if en.kind == "batch" and en.seq > self.seq:
                    self._wait_hold(en.position)
                    self._apply(en)
                elif en.kind == "delete":
                    raise FieldNotFoundError(f"field {self.field_id} deleted")
            with self._cond:
                self.through = en.position
                self._cond.notify_all()
        return bool(entries)

    def _wait_hold(self, position: int) -> None:
        """A snapshot holds this worker at a position before ``position``: wait."""
        with self._cond:
            while self._hold is not None and position > self._hold and not self._stop.is_set():
                self._cond.wait(0.5)

    def _apply(self, en) -> None:
        spec = self.spec
        t0 = time.perf_counter()
        flats, values, unit = read_batch(self.storage, self.field_id, en.seq, spec)
        adopt_unit(self.field, unit)
        t1 = time.perf_counter()
        prepared = self.field.prepare(flats, values, only=self.only)
        t2 = time.perf_counter()
        res = self.field.insert_prepared(prepared, slice_rows=self.settings.insert_slice_rows)
        cells = int(self.field.nsimplex)
        with self._cond:
            self.seq, self.position, self.cells = en.seq, en.position, cells
            self._duplicates[en.position] = int(res.duplicates)
            while len(self._duplicates) > KEEP_DUPLICATES:
                self._duplicates.popitem(last=False)
            self._cond.notify_all()
        log.debug("shard %s of field %d: batch %d (%d rows) applied: read %.3f s, prepare "
                  "%.3f s, insert %.3f s", self.charts, self.field_id, en.seq, en.nrows,
                  t1 - t0, t2 - t1, time.perf_counter() - t2)

    # -- answers --------------------------------------------------------------------------
    def _await(self, position: int, timeout: float, what: str) -> None:
        """Wait until every log entry up to ``position`` is applied here."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                if self.state is FieldState.FAILED:
                    raise ShardUnavailableError(f"shard {list(self.charts)} of field "
                                                f"{self.field_id}: {self.error}")
                if self.state is FieldState.READY and self.through >= position:
                    return
                left = end - time.monotonic()
                if left <= 0:
                    where = "restoring" if self.state is not FieldState.READY else \
                        f"at log position {self.through}"
                    raise ShardUnavailableError(
                        f"shard {list(self.charts)} of field {self.field_id}: {what} needs log "
                        f"position {position}; the shard is {where} (waited {timeout:g} s)")
                self._cond.wait(min(left, 0.5))

    def query(self, work, kw: dict, at_position: int, timeout: float):
        """Its charts' answers on the rows routed to them, once the log up to
        ``at_position`` is applied here (:meth:`flatserve.contract.SampledField.query_shards`).

        Parameters
        ----------
        work : list of (int, Flats)
            ``(chart, flats)`` pairs of this worker's charts.
        kw : dict
            ``outside``, ``order``, ``threads``, ``return_weights``, ``interpolant``.
        at_position : int
        timeout : float
            Seconds to wait for ``at_position``.

        Raises
        ------
        ShardUnavailableError
            Not there within ``timeout`` (restoring, or behind), or failed.
        """
        self._await(at_position, timeout, "a query")
        return self.field.query_shards(work, **kw)

    def applied(self, position: int, timeout: float) -> dict:
        """:meth:`status` once the log up to ``position`` is applied here (an upload
        with ``wait=true`` is answered once every group has its batch: its samples
        are then the field's), with ``duplicates``: the rows of the batch at
        ``position`` that coincided with a sample already in their own chart here
        (each row's own chart is in one group: the groups' sum is the field's),
        None when this worker did not apply that batch itself (restored past it).

        Raises
        ------
        ShardUnavailableError
            Not there within ``timeout`` (restoring, or behind), or failed.
        """
        self._await(position, timeout, "an upload")
        with self._cond:
            dups = self._duplicates.get(position)
        return {**self.status(), "duplicates": dups}

    def parts(self, position: int, known, timeout: float) -> dict:
        """Store its charts' snapshot parts with exactly the field's batches up to
        log ``position`` (:meth:`~flatserve.service.backend.LogBackend.store_part`:
        the parts go from here to the database, never through the front that
        writes the snapshot); the worker is held there (it applies no later batch
        of its field) while it serialises. Charts are serialised and stored one
        at a time (memory: one chart's part), and those whose part is ``known``
        (stored already) not at all. Calls run one at a time (a second waits up to
        ``timeout`` for the first): each holds the worker at its own position.

        Returns
        -------
        dict
            ``seq`` (the field's last batch up to ``position``), ``parts``
            (``[(chart, key), ...]``) or, for a one-chart field, ``whole`` (the
            key of the part holding the whole field file: the snapshot file is
            :func:`flatserve.contract.part_pointer` of it; for a field in tiles,
            the field file names a part per tile, ``tiles``, each stored only
            when its tile changed), ``own`` (per chart
            its own samples), ``nrejected``, ``stored`` (bytes this call stored),
            ``unit`` (an atlas field's unit of length, once chosen; else None).

        Raises
        ------
        ShardAheadError
            The worker has applied a later batch of its field already.
        ShardUnavailableError
            Not at ``position`` within ``timeout``, or another call's parts still
            being stored then.
        """
        if not self._parts_lock.acquire(timeout=max(timeout, 0.0)):
            raise ShardUnavailableError(
                f"shard {list(self.charts)} of field {self.field_id}: another snapshot's parts "
                f"were still being stored after {timeout:g} s; retry the snapshot")
        try:
            return self._parts(position, known, timeout)
        finally:
            self._parts_lock.release()

    def _parts(self, position: int, known, timeout: float) -> dict:
        """:meth:`parts`, one call at a time."""
        with self._cond:
            if self.position > position:
                raise ShardAheadError(
                    f"shard {list(self.charts)} of field {self.field_id} is at log position "
                    f"{self.position}, past {position}; retry the snapshot")
            self._hold = position
        try:
            self._await(position, timeout, "a snapshot")
            fld, known, stored = self.field, frozenset(known), 0
            own = getattr(fld, "own_samples", None)
            parts, whole, tiles = [], None, []
            if hasattr(fld, "chart_parts"):
                for c in self.charts:
                    ((_, key, blob),) = fld.chart_parts([c], known)
                    if blob is not None:
                        stored += self.storage.store_part(self.field_id, key, blob)
                    parts.append((c, key))
            elif fld.tiles != 1:  # one chart in tiles: a part per tile, and the field file
                with tempfile.TemporaryDirectory(prefix="flatserve-tiles-") as stage:
                    buf = io.BytesIO()
                    before = self.tile_host.stored  # (tiles that store their own parts)
                    tiles = fld.write_parts(buf, stage, known)
                    stored += self.tile_host.stored - before
                    for key in tiles:  # those changed since their part was stored
                        path = os.path.join(stage, key)
                        if os.path.exists(path):
                            with open(path, "rb") as fh:
                                stored += self.storage.store_part(self.field_id, key, fh.read())
                blob = buf.getvalue()
                whole = part_key(blob)
                if whole not in known:
                    stored += self.storage.store_part(self.field_id, whole, blob)
            else:  # one chart: its file is the field's
                blob = fld.to_bytes()
                whole = part_key(blob)
                if whole not in known:
                    stored += self.storage.store_part(self.field_id, whole, blob)
                del blob
            unit = None if getattr(fld, "unit_pending", True) else fld.atlas.unit
            return {"seq": self.seq, "parts": None if whole else parts, "whole": whole,
                    "tiles": tiles,
                    "unit": unit,
                    "own": None if own is None else [own[c] for c in self.charts],
                    "nrejected": fld.nrejected, "stored": stored}
        finally:
            with self._cond:
                self._hold = None
                self._cond.notify_all()

    def status(self) -> dict:
        """What the worker holds and where it is in the log (cheap; never waits)."""
        fld = self.field
        own = getattr(fld, "own_samples", None) if fld is not None else None
        return {
            "field_id": self.field_id, "charts": list(self.charts), "state": self.state.value,
            "error": self.error, "through": self.through, "seq": self.seq,
            "position": self.position,
            "nsamples": (sum(own[c] for c in self.charts) if own is not None
                         else (fld.nsamples if fld is not None else 0)),
            "nstored": int(fld.nstored) if fld is not None else 0,
            "nsimplex": self.cells,
            "nrejected": int(fld.nrejected) if fld is not None else 0,
            "chart_samples": [int(fld.shards[c].nsamples) for c in self.charts]
            if fld is not None else [0] * len(self.charts),
            # per chart, its own samples (a dense seam's charts narrow after enough)
            "chart_own": [int(own[c]) for c in self.charts] if own is not None
            else [None] * len(self.charts),
            "restored_from": self.restored_from, "rss": rss_bytes(), "pid": os.getpid(),
        }
