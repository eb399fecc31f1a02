"""The log applier: what a log entry does to this replica's fields.

Owned by the log follower (:mod:`.replica`), which reads the shared log and
hands each entry here in log order: a ``create`` registers a field in the
catalogue (:mod:`.catalogue`), a ``delete`` removes it, a ``batch`` is inserted
into its field (charted first unless this process charted it for its upload),
a ``snapshot`` points the entry at the newest snapshot. Restore is the same
work from storage: on start every stored field is registered (``LOADING``) and
restored from its newest snapshot plus its batches up to the log head read
with it (:meth:`LogApplier.restore_all`); a field whose memory may disagree
with storage (an insert failed half-way) is rebuilt the same way
(:meth:`LogApplier.rebuild`) before the follower goes on.

Every replica applies the same entries through this code (chart, then insert
in slices of ``insert_slice_rows``), so replicas at one position hold
bit-identical fields. A cluster's shard worker (:mod:`..cluster.worker.shard`) is this
same applier restricted to one field (``fields``) and to its charts (its
home's ``only``: :class:`LocalHome`), with no snapshot writer of its own
(the field's snapshot is its front's, in parts): the same restore, the same
retries, the same states, the same calls on those charts.
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from typing import Callable, TypeVar

from ...contract import load_field
from ...errors import SnapshotError
from ...field import AddResult, PreparedBatch
from ...flats import Flats
from ...tiles import TileHost, hosting
from ..log.backend import LogBackend
from ..log.rows import FieldRow, LogEntry, SnapshotGoneError
from ..log.blobs import split_batch
from .catalogue import FieldCatalogue, FieldState
from .entry import FieldEntry, FieldSpec, SampledField
from ..settings import Settings
from .snapshots import SnapshotWriter
from .specs import stored_spec
from ..status import (FieldNotFoundError, NotReadyError, ShardUnavailableError, StorageError,
                     StorageUnavailableError)
from .units import adopt_unit, batch_unit, unit_of

log = logging.getLogger("flatserve.service")

PROGRESS_EVERY_S = 2.0
#: a restore that found the database unreachable tries again after this many seconds
RESTORE_RETRY_S = 1.0


T = TypeVar("T")


class Stopped(Exception):
    """The applier was asked to stop in the middle of an entry."""


def until_reachable(attempt: Callable[[], T], stopping: Callable[[], bool],
                    wait: Callable[[float], object], what: str,
                    errors: tuple[type[Exception], ...] = (StorageUnavailableError,),
                    on_retry: Callable[[Exception], object] | None = None) -> T:
    """``attempt()``, tried again while the database is unreachable: the restore's
    retry, one rule for every process that restores from the log (a replica's
    applier, which a shard worker, :mod:`..cluster.worker.shard`, runs too).

    Parameters
    ----------
    attempt : callable
        The work; its result is returned.
    stopping : callable
        True once the caller is stopping: the last error is then raised.
    wait : callable
        Waits the given seconds (:data:`RESTORE_RETRY_S`) before the next try.
    what : str
        The warning's subject (``"field 'x': restore interrupted"``).
    errors : tuple of exception types
        Those that mean "unreachable, try again" (default
        :class:`~..status.StorageUnavailableError`); any other is raised at once.
    on_retry : callable, optional
        Told of each such error before the wait.
    """
    while True:
        try:
            return attempt()
        except errors as exc:
            if stopping():
                raise
            log.warning("%s: %s; retrying in %g s", what, exc, RESTORE_RETRY_S)
            if on_retry is not None:
                on_retry(exc)
            wait(RESTORE_RETRY_S)


def decided(prepared) -> None:
    """Chart a prepared batch's decisions now: a remote field's prepare charts them
    when they are first read (:class:`~flatserve.service.cluster.front.remote.RemoteField`),
    a local field's at once."""
    _ = prepared.accepted  # (the first read charts them)


def prepare_for(fld, flats: Flats, values, only):
    """``fld.prepare`` of a stored batch, for the charts in ``only`` alone (None: all)."""
    if only is None:
        return fld.prepare(flats, values)
    return fld.prepare(flats, values, only=only)


def stored_flats(e: FieldEntry, form: str | None, arrays: dict) -> Flats:
    """The :class:`Flats` of a stored batch (its arrays by name; the form is
    inferred from the names when None)."""
    return Flats.from_arrays(arrays, k=e.spec.k, d=e.spec.d, form=form)


def read_batch(storage: LogBackend, field_id: int, seq: int, spec: FieldSpec,
               form: str | None = None) -> tuple[Flats, object, float | None]:
    """A stored batch as every applier of the log inserts it (a replica's, a shard
    worker's): its :class:`Flats` (the form inferred from its arrays' names when
    None), its values, and the unit of length recorded with it
    (:func:`..log.blobs.split_batch`).

    Raises
    ------
    FieldNotFoundError
        The field was deleted meanwhile.
    """
    arrays, values, unit = split_batch(storage.batch_arrays(field_id, seq))
    return Flats.from_arrays(arrays, k=spec.k, d=spec.d, form=form), values, unit


def entry_of(row: FieldRow, state: FieldState = FieldState.LOADING) -> FieldEntry:
    """The entry of a stored field's row (its field not built yet), its definition
    checked as a create's (:func:`.specs.stored_spec`) before anything is built
    from it.

    Raises
    ------
    InvalidInputError
        The stored definition holds a value no create accepts (an entry written by
        hand or by a faulty version): the caller registers :func:`failed_entry`.
    """
    basis = row.basis if isinstance(row.basis, dict) else {}
    spec, basis = stored_spec(row.spec, basis.get("Q"), basis.get("r"))
    return FieldEntry(row.id, row.name, spec, basis, row.created, row.snapshot_file,
                      row.snapshot_seq, state=state, position=row.position,
                      snapshot_position=row.snapshot_position)


def failed_entry(row: FieldRow, exc: Exception) -> FieldEntry:
    """A stored field whose entry cannot be built (:func:`entry_of` raised ``exc``):
    ``FAILED``, no basis, its spec's sizes where readable (else 0) and nothing else
    of it (nothing is built from it; its requests get a 503 naming ``exc``)."""
    try:
        spec = FieldSpec.from_dict(row.spec)
        spec = FieldSpec(spec.k, spec.d, spec.channels, {})
    except Exception:
        spec = FieldSpec(0, 0, 0, {})
    return FieldEntry(row.id, row.name, spec, None, row.created, row.snapshot_file,
                      row.snapshot_seq, state=FieldState.FAILED, position=row.position,
                      error=f"its stored definition cannot be read: {exc}")


class LocalHome:
    """Fields held in this process, built and restored by this applier (the default
    home, :mod:`..assembly`; a shard worker's, with ``only``, :mod:`..cluster.worker.shard`).

    Parameters
    ----------
    only : collection of int, optional
        The charts held here (a shard worker's; a one-chart field's one shard is
        chart 0): the others stay empty, a batch is charted for these only
        (``prepare(only=)``) and a snapshot restores these only. Default: every one.
    tile_host : TileHost, optional
        Where a tiled field's tiles live (:func:`flatserve.tiles.hosting`); default:
        this process.
    """

    #: the fields' shards live elsewhere: nothing to load or replay here
    remote = False

    def __init__(self, only=None, tile_host: TileHost | None = None) -> None:
        self.only = None if only is None else frozenset(int(c) for c in only)
        self.tile_host = tile_host

    def _hosting(self):
        return nullcontext() if self.tile_host is None else hosting(self.tile_host)

    def field(self, e: FieldEntry, built: SampledField | None = None) -> SampledField:
        """The field of entry ``e`` (``built``: the one its create request made)."""
        if built is not None:
            return built
        with self._hosting():
            return e.spec.new_field(e.basis)

    def load(self, path, parts) -> SampledField:
        """The field of a snapshot file (:func:`flatserve.contract.load_field`; its
        charts in ``only`` alone).

        Raises
        ------
        SnapshotError
            Damaged, or (``only`` set) an older snapshot without its charts' own
            samples (a shard restored alone could not count its share).
        ShardUnavailableError
            A tile of ``tile_host`` was lost meanwhile (not the snapshot's fault).
        """
        try:
            with self._hosting():
                fld = load_field(path, parts, only=self.only)
        except Exception as exc:
            lost = getattr(self.tile_host, "lost", None)
            if lost:
                raise ShardUnavailableError(f"a tile was lost: {lost}") from exc
            raise
        if self.only is not None and fld.own_samples is None:
            raise SnapshotError("an older snapshot without its charts' own samples")
        return fld

    def drop(self, e: FieldEntry) -> None:
        """``e`` was deleted (its memory goes with the entry)."""

    def close(self) -> None:
        pass


class LogApplier:
    """Applies log entries and restores fields (the follower's thread; see the module doc).

    Parameters
    ----------
    settings : Settings
    storage : LogBackend
    catalogue : FieldCatalogue
        Where entries are registered.
    snapshots : SnapshotWriter or None
        Asked for a background snapshot after inserts (``snapshot_every``); None:
        this process writes no snapshot and cleans none up (a shard worker's).
    metrics : Metrics or None
    home : LocalHome or ClusterHome
        Where the fields' shards live (:mod:`..assembly`), chosen by the composition
        root (:meth:`..assembly.Rooms.open`, :func:`..assembly.open_home`); a home with
        ``only`` charts (a shard worker's) holds those charts alone.
    fields : collection of int, optional
        The ids of the fields applied here (a shard worker's one field); the log's
        entries of any other are passed over. Default: every field.
    on_batch : callable, optional
        ``on_batch(field_id, position, result)`` after each batch inserted (by the
        follower, or replayed by a restore), with its :class:`AddResult`.
    """

    def __init__(self, settings: Settings, storage: LogBackend, catalogue: FieldCatalogue,
                 snapshots: SnapshotWriter | None, metrics, home, *, fields=None,
                 on_batch: Callable[[int, int, AddResult], object] | None = None) -> None:
        self.settings = settings
        self.home = home
        #: the charts held here (None: every one)
        self.only = home.only
        self.fields = None if fields is None else frozenset(int(f) for f in fields)
        self.on_batch = on_batch
        self.storage = storage
        self.catalogue = catalogue
        self.snapshots = snapshots
        self.metrics = metrics
        #: per field id, what its last restore started from (``"snapshot after batch
        #: N"`` or ``"the log"``)
        self.restored_from: dict[int, str] = {}
        #: fields this process built for its own create (field id -> field)
        self._built: dict[int, SampledField] = {}
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._restore_head = 0

    def stop(self) -> None:
        """Stop between the steps of an entry (:class:`Stopped`) and stop restoring."""
        self._stopping.set()

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    # -- a create's own field ---------------------------------------------------------------
    def offer_built(self, field_id: int, fld: SampledField) -> None:
        """The field a create request built: its create entry uses it (not built twice)."""
        with self._lock:
            self._built[field_id] = fld

    def withdraw_built(self, field_id: int | None) -> None:
        with self._lock:
            self._built.pop(field_id, None)

    def built_count(self) -> int:
        """Fields offered by creates and not yet taken or withdrawn (0 at rest)."""
        with self._lock:
            return len(self._built)

    # -- entries ----------------------------------------------------------------------------
    def note_pending(self, entries: list[LogEntry]) -> None:
        """The follower read these entries: count their batches as pending."""
        for en in entries:
            if en.kind == "batch":
                e = self.catalogue.by_id(en.field_id)
                if e is not None:
                    e.add_pending(en.position, en.nrows, keep=True)

    def _mine(self, field_id: int) -> bool:
        return self.fields is None or field_id in self.fields

    def apply_create(self, entry: LogEntry) -> None:
        if not self._mine(entry.field_id):
            return
        try:
            row = self.storage.field(entry.field_id)
        except FieldNotFoundError:
            return  # deleted later in the log: its delete entry follows
        with self._lock:
            fld = self._built.pop(row.id, None)
        try:
            e = entry_of(row, state=FieldState.READY)
            e.field = self.home.field(e, fld)
        except (StorageError, Stopped):
            raise
        except Exception as exc:  # a definition no create makes: that field only fails
            log.exception("field %r: its stored definition cannot be used", row.name)
            e = failed_entry(row, exc)
        self.catalogue.put(e)

    def apply_delete(self, entry: LogEntry) -> None:
        e = self.catalogue.remove(entry.field_id)
        if e is None:
            return
        with e.index_lock:
            e.deleted = True
        e.drop_pending()
        self.restored_from.pop(e.id, None)
        self.home.drop(e)

    def apply_snapshot(self, entry: LogEntry) -> None:
        e = self.catalogue.by_id(entry.field_id)
        if e is None or self.snapshots is None:
            return
        try:
            row = self.storage.field(entry.field_id)
        except FieldNotFoundError:
            return
        self.snapshots.adopt(e, row)

    def apply_batch(self, entry: LogEntry, prepared: PreparedBatch | None
                    ) -> tuple[AddResult | None, str | None]:
        """Insert the batch of a log entry (charting it unless this process did);
        ``(AddResult, None)``, or ``(None, why)`` if the insert failed (the field
        is then rebuilt from storage up to this entry), or ``(None, None)`` if
        there was nothing to insert (field deleted or not held).

        Raises
        ------
        Stopped
            The applier was stopped before the insert.
        """
        e = self.catalogue.by_id(entry.field_id)
        try:
            if e is None or e.deleted or e.state is not FieldState.READY or \
                    entry.seq <= e.indexed_seq:
                return None, None
            self._before_index(e, entry.seq)
            if self.stopping:
                raise Stopped()
            t0 = time.perf_counter()
            again = False
            if prepared is not None and getattr(prepared, "unit", None) is not None and \
                    prepared.unit != unit_of(e.field):
                # charted by the upload room in the unit stored with it: the field's first
                # batch sets the field's unit to it; a later one (another replica's batch
                # came first) is charted again in the field's unit
                adopt_unit(e.field, prepared.unit)
                if prepared.unit != unit_of(e.field):
                    prepared, again = None, True
            if prepared is None:
                try:
                    flats, values, unit = read_batch(self.storage, e.id, entry.seq, e.spec)
                except FieldNotFoundError:
                    return None, None  # deleted meanwhile: its delete entry follows
                adopt_unit(e.field, batch_unit(e.field, flats, values, unit))
                prepared = prepare_for(e.field, flats, values, self.only)
                if again:  # the upload that handed it over answers with these decisions
                    decided(prepared)
            try:
                with e.index_lock:
                    if e.deleted:
                        return None, None
                    res = e.field.insert_prepared(prepared,
                                                  slice_rows=self.settings.insert_slice_rows)
                    e.mark_indexed(entry.seq, entry.position)
                    e.new_samples += res.accepted
                    if self.on_batch is not None:
                        self.on_batch(e.id, entry.position, res)
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
                    self.metrics.accepted(e.name, res.accepted)
        finally:
            if e is not None:
                e.drop_pending(entry.position)
        if self.snapshots is not None:
            self.snapshots.maybe_snapshot(e)
        return res, None

    def fail_field(self, field_id: int, why: str) -> None:
        """Mark a field failed (its requests get a 503 naming ``why``)."""
        e = self.catalogue.by_id(field_id)
        if e is not None:
            e.mark_failed(why)

    @staticmethod
    def _before_index(e: FieldEntry, seq: int) -> None:
        """Called before batch ``seq`` of ``e`` is inserted (a test hook)."""

    # -- restore ----------------------------------------------------------------------------
    def restore_all(self) -> int | None:
        """Register every stored field (``LOADING``) and restore each to the log head
        read with them; that head (None if stopped first). Waits for the database."""
        try:  # the database unreachable: wait for it (never ready otherwise)
            head, rows = until_reachable(self.storage.state, lambda: self.stopping,
                                         self._stopping.wait, "restore", errors=(StorageError,))
        except StorageError:  # (stopping)
            return None
        self._restore_head = head
        if self.snapshots is not None:
            self.snapshots.clean_orphans()
        entries = []
        for row in rows:
            if not self._mine(row.id):
                continue
            try:
                e = entry_of(row)
            except Exception as exc:  # (a spec this version cannot read): that field only
                log.exception("field %r: its stored definition cannot be read", row.name)
                self.catalogue.put(failed_entry(row, exc))
                continue
            self.catalogue.put(e)
            entries.append((e, row))
        log.info("restoring %d stored field(s) from %s %s to log position %d", len(entries),
                 self.storage.kind, self.storage.where, head)
        # fields restore independently: each is ready as soon as it is loaded, and an
        # expensive one holds up only its own thread
        with ThreadPoolExecutor(self.settings.restore_threads,
                                thread_name_prefix="flatserve-restore") as pool:
            for e, row in entries:
                pool.submit(lambda e=e, row=row: None if self.stopping
                            else self._restore(e, row))
        return None if self.stopping else head

    def _load_snapshot(self, e: FieldEntry, row: FieldRow, upto: int
                       ) -> tuple[SampledField | None, FieldRow]:
        """The field of the row's snapshot (None if there is none, it is unusable, or
        it holds batches after log position ``upto``: a newer snapshot that replaced
        it meanwhile would carry the field past ``upto``) and the row it came from
        (re-read if the snapshot was replaced meanwhile)."""
        for _ in range(5):
            if not row.snapshot_file or row.snapshot_position > upto:
                return None, row
            t0 = time.perf_counter()
            try:
                fld = self.storage.load_snapshot(row, self.home.load)
            except SnapshotGoneError:
                row = self.storage.field(e.id)  # a newer one replaced it: take that
                continue
            except (StorageUnavailableError, NotReadyError):
                raise  # the database unreachable (retried), a tile lost (failed)
            except Exception as exc:  # corrupt/missing snapshot: rebuild from batches
                log.warning("field %r: snapshot %s unusable (%s); rebuilding from batches",
                            e.name, self.storage.snapshot_location(row), exc)
                return None, row
            log.info("field %r: snapshot after batch %d loaded (%d samples) in %.2f s",
                     e.name, row.snapshot_seq, fld.nsamples, time.perf_counter() - t0)
            return fld, row
        return None, row

    def _restore(self, e: FieldEntry, row: FieldRow, upto: int | None = None, *,
                 count: bool = True) -> None:
        """Restore ``e`` to log position ``upto`` (default: the head the start-up
        restore read): its snapshot, then its batches up to ``upto`` inserted as
        the follower inserts them (chart, insert in slices). The database
        unreachable meanwhile: tried again until it answers (or the applier stops).
        ``count``: the replayed samples are this replica's work (at its start;
        False for a rebuild, which replays what it already counted)."""
        if upto is None:
            upto = self._restore_head
        try:
            until_reachable(lambda: self._restore_once(e, row, upto, count),
                            lambda: self.stopping, self._stopping.wait,
                            f"field {e.name!r}: restore interrupted")
        except StorageUnavailableError as exc:  # (stopping)
            e.mark_failed(str(exc))

    def _restore_once(self, e: FieldEntry, row: FieldRow, upto: int, count: bool) -> None:
        t0 = time.perf_counter()
        if self.home.remote:  # its shards restore themselves where they live
            return self._restore_remote(e, upto)
        try:
            fld, row = self._load_snapshot(e, row, upto)
            start, start_pos = (row.snapshot_seq, row.snapshot_position) if fld is not None \
                else (0, 0)
            restored_from = "the log" if fld is None else f"snapshot after batch {start}"
            if fld is None:
                fld = self.home.field(e)
            todo = self.storage.batches(e.id, after_seq=start, upto_position=upto)
            nb = self.storage.batch_stats(e.id)[0]
            log.info("field %r: replaying %d of %d stored batch(es)", e.name, len(todo), nb)
            done, tlast, replayed = 0, time.perf_counter(), 0
            seq, pos = start, start_pos
            for b in todo:
                flats, values, unit = read_batch(self.storage, e.id, b.seq, e.spec, b.form)
                adopt_unit(fld, unit)
                prepared = prepare_for(fld, flats, values, self.only)
                res = fld.insert_prepared(  # (a tiled chart: each batch whole, settled)
                    prepared, slice_rows=self.settings.insert_slice_rows)
                replayed += int(res.accepted)
                if self.on_batch is not None:
                    self.on_batch(e.id, b.position, res)
                seq, pos = b.seq, b.position
                done += 1
                if time.perf_counter() - tlast > PROGRESS_EVERY_S:
                    log.info("field %r: replayed %d/%d batches (%d samples)", e.name, done,
                             len(todo), fld.nsamples)
                    tlast = time.perf_counter()
            e.field = fld
            e.mark_indexed(seq, pos)
            e.snapshot_file = row.snapshot_file if start else None
            e.snapshot_seq, e.snapshot_position = start, start_pos
            e.new_samples = replayed
            self.restored_from[e.id] = restored_from
            if count and self.metrics is not None and replayed:  # (a replica that
                self.metrics.accepted(e.name, replayed)  # started late triangulates them)
            e.mark_ready()
            log.info("field %r: restored, %d samples, %d batches replayed in %.2f s", e.name,
                     fld.nsamples, done, time.perf_counter() - t0)
            if self.snapshots is not None:
                self.snapshots.maybe_snapshot(e)
        except StorageUnavailableError:
            raise  # retried by _restore
        except Exception as exc:
            log.exception("field %r: restore failed", e.name)
            e.mark_failed(str(exc))

    def _restore_remote(self, e: FieldEntry, upto: int) -> None:
        """A field whose shards live elsewhere: its entry at the field's last batch up
        to ``upto`` (the shards load their snapshot and replay the log themselves)."""
        try:
            done = self.storage.batches(e.id, upto_position=upto)
            seq, pos = (done[-1].seq, done[-1].position) if done else (0, 0)
            e.field = self.home.field(e)
            if done and e.field.unit_pending:
                self._first_unit(e, done[0])
            e.mark_indexed(seq, pos)
            e.mark_ready()
            log.info("field %r: its shards live in the cluster; at batch %d", e.name, seq)
        except StorageUnavailableError:
            raise  # retried by _restore
        except Exception as exc:
            log.exception("field %r: restore failed", e.name)
            e.mark_failed(str(exc))

    def _first_unit(self, e: FieldEntry, first) -> None:
        """A remote field whose unit its first batch chooses takes the unit recorded
        with that batch; a batch stored before a front recorded it: the unit each
        shard worker chose from it (:func:`flatserve.atlas_field.choose_unit`)."""
        flats, values, unit = read_batch(self.storage, e.id, first.seq, e.spec, first.form)
        adopt_unit(e.field, batch_unit(e.field, flats, values, unit))

    def rebuild(self, e: FieldEntry, upto: int, why: str) -> None:
        """Rebuild a field from storage up to log position ``upto`` (the follower's
        thread: no later entry is applied meanwhile; queries get 503 until done)."""
        e.mark_loading(why)
        while True:
            try:
                row = self.storage.field(e.id)
                break
            except StorageUnavailableError as exc:  # as _restore: wait for the database
                if self.stopping:
                    e.mark_failed(str(exc))
                    return
                self._stopping.wait(RESTORE_RETRY_S)
            except Exception as exc:
                e.mark_failed(str(exc))
                return
        with e.upload_lock, e.index_lock:
            self._restore(e, row, upto, count=False)
