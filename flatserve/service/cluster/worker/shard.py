"""One shard group of one field, in a process of its own: the server's log engine on its charts.

A :class:`ShardWorker` has no log engine of its own: it is the server's
:class:`~...rooms.replica.Follower` over a :class:`~...rooms.applier.LogApplier`
restricted to its field and to its charts (a :class:`~...rooms.applier.LocalHome`
with ``only=charts``), as every Qdrant peer runs the same local shard code: it
restores, retries, follows and fails by the server's rules and states. What it
adds are its answers (:class:`..wire.ShardCalls`: :meth:`~ShardWorker.query`,
:meth:`~ShardWorker.applied`, :meth:`~ShardWorker.parts`, :meth:`~ShardWorker.status`).
Where it lives (a Ray actor, :mod:`.actor`; a thread in tests) is not its business.
docs/design.md, "A shard worker".
"""
from __future__ import annotations

import io
import logging
import os
import tempfile
import threading
import time
from collections import OrderedDict

from ....contract import part_key
from ....tiles import TileHost
from ...rooms.applier import LocalHome, LogApplier, until_reachable
from ...log.backend import LogBackend, open_backend
from ...rooms.catalogue import FieldCatalogue, FieldState
from ...rooms.replica import Follower
from ...status import NotReadyError, ShardUnavailableError, StorageError
from ..ray_env import rss_bytes

log = logging.getLogger("flatserve.service.cluster")

#: batches whose duplicates a worker remembers (the latest applied; an upload with
#: ``wait=true`` asks for its own at once)
KEEP_DUPLICATES = 256


class ShardAheadError(NotReadyError):
    """A snapshot asked a shard for its charts at a log position it has passed
    (the field's other shards are behind it): the snapshot is tried again later."""


class ShardWorker:
    """Some charts of one field, following the log (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``database_url`` (unset: the SQLite database of ``data_dir``, read as a
        follower), ``insert_slice_rows`` (the fronts': a chart's bits depend on it).
    field_id : int
    charts : sequence of int
        The charts this worker holds.
    storage : LogBackend, optional
        Default: :func:`~flatserve.service.log.backend.open_backend` of ``settings`` as
        a follower, opened by the worker's thread (unreachable: tried again).
    tile_host : TileHost, optional
        Where a tiled field's tiles live (a Ray actor's: :class:`~.tiles.RayTileHost`);
        default: this process.
    start : bool
        Start restoring and following at once (default).
    """

    def __init__(self, settings, field_id: int, charts, *, storage: LogBackend | None = None,
                 tile_host: TileHost | None = None, start: bool = True) -> None:
        self.settings = settings
        self.field_id = int(field_id)
        self.charts = tuple(sorted(int(c) for c in charts))
        self.tile_host = tile_host or TileHost()
        #: where its charts live: this process, its tiles with ``tile_host``
        self.home = LocalHome(only=self.charts, tile_host=self.tile_host)
        self._storage = storage
        #: its one field's entry (state, field, last batch applied), as a replica's
        self.catalogue = FieldCatalogue()
        #: the server's follower over an applier of its field and charts (made by
        #: the worker's thread once the log is open)
        self.follower: Follower | None = None
        #: per log position of a batch applied here (the latest :data:`KEEP_DUPLICATES`),
        #: the rows of its charts' own that coincided with a sample already held
        self._duplicates: OrderedDict[int, int] = OrderedDict()
        self._lock = threading.Lock()
        #: one snapshot's parts at a time: each holds the follower at its own position
        #: and counts the bytes its tiles stored
        self._parts_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="flatserve-shard", daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop following (between two entries) and close the storage."""
        self._stop.set()
        with self._lock:
            fo = self.follower
        if fo is not None:
            fo.stop(0.0)
        elif self._storage is not None:
            self._storage.wake()
        if self._thread.is_alive():
            self._thread.join(timeout)
        if fo is not None:
            fo.join(timeout)
        if self._storage is not None:
            self._storage.close()

    @property
    def storage(self) -> LogBackend:
        return self._open()

    # -- the engine: the server's ---------------------------------------------------------
    def _open(self) -> LogBackend:
        if self._storage is None:
            self._storage = open_backend(self.settings, follower=True)
        return self._storage

    def _run(self) -> None:
        what = f"shard {list(self.charts)} of field {self.field_id}"
        try:  # the database unreachable: tried again (queries wait)
            storage = until_reachable(self._open, self._stop.is_set, self._stop.wait,
                                      f"{what}: opening the log", errors=(StorageError,))
        except StorageError:  # (stopping)
            return
        applier = LogApplier(self.settings, storage, self.catalogue, None, None, self.home,
                             fields=(self.field_id,), on_batch=self._batch_applied)
        with self._lock:
            if self._stop.is_set():
                return
            self.follower = Follower(storage, applier)
        self.follower.restore_and_follow()

    def _batch_applied(self, field_id: int, position: int, res) -> None:
        with self._lock:
            self._duplicates[position] = int(res.duplicates)
            while len(self._duplicates) > KEEP_DUPLICATES:
                self._duplicates.popitem(last=False)

    @property
    def _entry(self):
        return self.catalogue.by_id(self.field_id)

    def _state(self) -> tuple[FieldState, str | None]:
        """``LOADING`` (opening the log, restoring, rebuilding), ``READY`` (following
        the log, answering) or ``FAILED``, and why (a defect, or the field was deleted)."""
        e = self._entry
        if e is not None:
            return e.state, e.error
        if self.catalogue.ready.is_set():  # restored and following, and no entry
            return FieldState.FAILED, "the field was deleted"
        return FieldState.LOADING, None

    @property
    def field(self):
        """Its charts' field (None until restored)."""
        e = self._entry
        return None if e is None else e.field

    @property
    def through(self) -> int:
        """Every log entry up to this position is applied here."""
        fo = self.follower
        return 0 if fo is None else fo.applied

    @property
    def seq(self) -> int:
        """The field's last batch applied here (and :attr:`position`, its log position)."""
        e = self._entry
        return 0 if e is None else e.indexed_seq

    @property
    def position(self) -> int:
        e = self._entry
        return 0 if e is None else e.indexed_position

    @property
    def restored_from(self) -> str | None:
        """``"snapshot after batch N"`` or ``"the log"`` (None: not restored yet)."""
        fo = self.follower
        return None if fo is None else fo.applier.restored_from.get(self.field_id)

    # -- answers --------------------------------------------------------------------------
    def _await(self, position: int, timeout: float, what: str) -> None:
        """Wait until every log entry up to ``position`` is applied here."""
        end = time.monotonic() + timeout
        while True:
            state, error = self._state()
            fo, through = self.follower, self.through
            if state is FieldState.FAILED or self._stop.is_set():
                raise ShardUnavailableError(f"shard {list(self.charts)} of field "
                                            f"{self.field_id}: {error or 'stopping'}")
            if state is FieldState.READY and through >= position:
                return
            left = end - time.monotonic()
            if left <= 0:
                where = "restoring" if state is not FieldState.READY else \
                    f"at log position {through}"
                raise ShardUnavailableError(
                    f"shard {list(self.charts)} of field {self.field_id}: {what} needs log "
                    f"position {position}; the shard is {where} (waited {timeout:g} s)")
            if fo is not None and through < position:
                fo.wait_applied(position, min(left, 0.5))  # (woken once applied)
            else:  # opening the log, restoring, rebuilding
                self._stop.wait(min(left, 0.05))

    def query(self, work, kw: dict, at_position: int, timeout: float):
        """Its charts' answers (:meth:`flatserve.contract.SampledField.query_shards` of
        ``work``, ``(chart, flats)`` pairs, with ``kw``) once the log up to
        ``at_position`` is applied here (ShardUnavailableError: not within
        ``timeout``, or failed)."""
        self._await(at_position, timeout, "a query")
        return self.field.query_shards(work, **kw)

    def applied(self, position: int, timeout: float) -> dict:
        """:meth:`status` once the log up to ``position`` is applied here, with
        ``duplicates``: the rows of the batch at ``position`` that coincided with a
        sample already in their own chart here (None: this worker restored past
        that batch). ShardUnavailableError: not within ``timeout``, or failed."""
        self._await(position, timeout, "an upload")
        with self._lock:
            dups = self._duplicates.get(position)
        return {**self.status(), "duplicates": dups}

    def parts(self, position: int, known, timeout: float) -> dict:
        """Store its charts' snapshot parts with exactly the field's batches up to log
        ``position``, held there meanwhile (from here to the database, never through
        the front), one chart at a time and those ``known`` not at all; one call at a
        time (a second waits up to ``timeout``).

        Returns
        -------
        dict
            ``seq`` (the field's last batch up to ``position``), ``parts``
            (``[(chart, key), ...]``) or, for a one-chart field, ``whole`` (the key
            of the part holding the field file; in tiles, it names a part per tile,
            ``tiles``), ``own`` (per chart its own samples), ``nrejected``,
            ``stored`` (bytes stored), ``unit`` (an atlas field's unit, once chosen).

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
        end = time.monotonic() + timeout
        if self.follower is None:  # (the log not open yet)
            self._await(position, timeout, "a snapshot")
        assert self.follower is not None
        with self.follower.held(position):
            if self.position > position:
                raise ShardAheadError(
                    f"shard {list(self.charts)} of field {self.field_id} is at log position "
                    f"{self.position}, past {position}; retry the snapshot")
            self._await(position, max(0.0, end - time.monotonic()), "a snapshot")
            fld, known = self.field, frozenset(known)
            stored, parts, whole, tiles, own = 0, [], None, [], None

            def put(key: str, blob: bytes | None) -> None:
                nonlocal stored
                if blob is not None and key not in known:
                    stored += self.storage.store_part(self.field_id, key, blob)

            # (the one place a shard asks its field's kind: how its snapshot is cut)
            if fld.blends:  # an atlas field: a part per chart, with its own samples
                own = fld.own_samples
                for c in self.charts:
                    ((_, key, blob),) = fld.chart_parts([c], known)
                    put(key, blob)
                    parts.append((c, key))
            else:  # one chart: its file is the field's (in tiles: naming a part per tile)
                if fld.tiles == 1:
                    blob = fld.to_bytes()
                else:
                    with tempfile.TemporaryDirectory(prefix="flatserve-tiles-") as stage:
                        buf, before = io.BytesIO(), self.tile_host.stored
                        tiles = fld.write_parts(buf, stage, known)
                        stored += self.tile_host.stored - before  # (tiles storing their own)
                        for key in tiles:  # those changed since their part was stored
                            path = os.path.join(stage, key)
                            if os.path.exists(path):
                                with open(path, "rb") as fh:
                                    put(key, fh.read())
                    blob = buf.getvalue()
                whole = part_key(blob)
                put(whole, blob)
                del blob
            return {"seq": self.seq, "parts": None if whole else parts, "whole": whole,
                    "tiles": tiles, "unit": fld.unit, "nrejected": fld.nrejected,
                    "own": None if own is None else [own[c] for c in self.charts],
                    "stored": stored}

    def status(self) -> dict:
        """What the worker holds and where it is in the log (cheap; never waits)."""
        e, (state, error) = self._entry, self._state()
        st = {"field_id": self.field_id, "charts": list(self.charts), "state": state.value,
              "error": error, "through": self.through, "seq": self.seq,
              "position": self.position, "restored_from": self.restored_from,
              "rss": rss_bytes(), "pid": os.getpid()}
        fld = None if e is None else e.field
        if fld is None:
            return {**st, "nsamples": 0, "nstored": 0, "nsimplex": 0, "nrejected": 0,
                    "chart_samples": [0] * len(self.charts),
                    "chart_own": [None] * len(self.charts)}
        own = fld.own_samples  # (per chart: a dense seam's charts narrow after enough)
        return {
            **st, "nstored": int(fld.nstored), "nrejected": int(fld.nrejected),
            "nsamples": sum(own[c] for c in self.charts) if own is not None else fld.nsamples,
            # the cells after the last batch applied (counted then: a tiled field
            # counts its tiles' cells under its lock, which an insert holds)
            "nsimplex": e.complete_size[1],
            "chart_samples": [int(fld.shards[c].nsamples) for c in self.charts],
            "chart_own": [int(own[c]) for c in self.charts] if own is not None
            else [None] * len(self.charts),
        }
