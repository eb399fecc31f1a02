"""The storage interface of a replica: a log of field operations plus snapshots.

Every server process is a *replica*: it restores each field from the newest
snapshot plus the log after it, then follows the log and applies its entries
in log order (:mod:`..rooms.replica`, written once for every backend). What a backend
stores, and how, is behind :class:`LogBackend`; the SQL lives in the backend
classes only:

* :class:`flatserve.service.log.storage.SQLiteBackend`: SQLite in the data
  directory (one machine; the embedded default), snapshot files beside it;
* a PostgreSQL backend (``FLATSERVE_DATABASE_URL=postgresql://...``), chosen by
  :func:`open_backend` from the URL's scheme (:data:`BACKENDS`).

The log
-------
Every change of the stored fields appends one :class:`LogEntry` **in the same
transaction** as the change: ``create`` (a field), ``delete`` (a field, with its
batches and snapshot), ``batch`` (one upload) and ``snapshot`` (a snapshot was
written: an announcement, no change of a field's samples). Each entry has a
*position*, an integer that is strictly increasing in **commit order**: once an
entry at position ``p`` is visible to a reader, every entry at a position below
``p`` that will ever be committed is visible too (positions may have gaps, e.g.
after a rolled-back transaction; a follower never waits for a gap to fill).
SQLite gets this for free (one writer at a time: an ``AUTOINCREMENT`` key
taken inside the write transaction); a backend with concurrent writers must
serialise the appends (e.g. a transaction-level lock taken before the position
is drawn). An upload is acknowledged only after its transaction committed.

Per field, batches are numbered ``seq`` = 1, 2, ... in commit order (the
``batch`` number of the HTTP API; ``seq`` increases with ``position``); the
idempotency key is unique per field (a second batch with a key already stored
is refused with :class:`~.rows.KeyTakenError`, whichever replica stored the first).

Threads
-------
A backend is used by many threads of one process at once (request handlers,
the log follower, the snapshot writer): every method is thread-safe.
:meth:`LogBackend.wait_for_change` is called by one thread only (the follower).
Errors of the database are raised as :class:`flatserve.service.status.StorageError`
(:class:`~flatserve.service.status.StorageFullError` when out of space: a 507), never as
the driver's own exceptions.
"""
from __future__ import annotations

import abc
import importlib
import os
import socket
import uuid
from pathlib import Path
from typing import Callable, Literal, Sequence, TypeVar

import numpy as np

from .rows import BatchRow, FieldRow, LogEntry, SnapshotGoneError, SnapshotInfo

T = TypeVar("T")

#: the kinds of log entries
EntryKind = Literal["create", "delete", "batch", "snapshot"]

#: seconds :meth:`LogBackend.clean_orphans` holds a field's snapshot lease
CLEAN_LEASE_S = 60.0


def snapshot_lease(field_id: int) -> str:
    """The name of field ``field_id``'s snapshot lease: one writer of a field's
    snapshots at a time across replicas, whatever the other fields' writers do
    (field ids are never reused, so neither are these names).

    Everything that removes snapshot data a field does not point at relies on
    it: a snapshot's own pointing (the former snapshot, the parts it no longer
    names), an abandoned snapshot's parts, and :meth:`LogBackend.clean_orphans`
    for a field that exists; a field's data is the field's only (its names and
    rows carry the field's id), so two fields' writers never touch each other's.
    """
    return f"snapshot:{int(field_id)}"


def lease_owner(tag: str = "") -> str:
    """A new lease owner ``"<hostname>:<pid>:<random>"`` (``tag`` appended to the
    random part): the form :meth:`LogBackend.acquire_lease` expects, by which a
    backend may tell a dead process of this host."""
    return f"{socket.gethostname()}:{os.getpid()}:{tag}{uuid.uuid4().hex[:8]}"


class LogBackend(abc.ABC):
    """Durable state shared by the replicas: fields, batches, the log, snapshots.

    See the module doc for the log's guarantees. ``kind`` names the backend
    (``"sqlite"``, ``"postgresql"``); ``where`` says where it stores (for logs
    and errors; never a password).
    """

    kind: str = "?"
    where: str = "?"

    # -- life cycle ---------------------------------------------------------------
    @abc.abstractmethod
    def check(self) -> None:
        """Refuse damaged storage (a quick consistency check at start).

        Raises
        ------
        flatserve.service.status.StorageError
            Naming what is damaged and what to do.
        """

    @abc.abstractmethod
    def close(self) -> None:
        """Release connections and locks (idempotent). A :meth:`wait_for_change`
        in progress returns."""

    # -- writes: each appends one log entry in its own transaction ---------------
    @abc.abstractmethod
    def create_field(self, name: str, spec: dict, basis: dict[str, np.ndarray]) -> tuple[int, int]:
        """Store a new field and its ``create`` entry; durable on return.

        Parameters
        ----------
        name : str
        spec : dict
            JSON-serialisable (stored as given, returned in :attr:`FieldRow.spec`).
        basis : dict of str to ndarray
            ``{"Q": (m, d, d), "r": (m, d)}`` float64.

        Returns
        -------
        (field_id, position) : (int, int)

        Raises
        ------
        flatserve.service.status.FieldExistsError
            A stored field has this name.
        """

    @abc.abstractmethod
    def delete_field(self, field_id: int) -> int:
        """Remove a field, its batches, their responses and its snapshot; append its
        ``delete`` entry. Durable on return (snapshot data may be removed after
        the commit, best effort).

        Returns
        -------
        position : int

        Raises
        ------
        flatserve.service.status.FieldNotFoundError
            No stored field has this id (deleted meanwhile, e.g. by another replica).
        """

    @abc.abstractmethod
    def add_batch(self, field_id: int, *, idem_key: str | None, chash: str, form: str,
                  nrows: int, blob: bytes,
                  result_fn: Callable[[int, int], dict] | None = None) -> tuple[int, int]:
        """Store one batch and its ``batch`` entry; durable (fsync'd) on return.

        The batch's ``seq`` is the field's largest seq plus one (and above its
        ``snapshot_seq``), drawn inside the transaction.

        Parameters
        ----------
        field_id : int
        idem_key : str or None
            Unique per field among stored batches.
        chash : str
            Content hash (:func:`flatserve.service.log.blobs.content_hash`).
        form : str
        nrows : int
        blob : bytes
            The arrays, :func:`flatserve.service.log.blobs.pack_arrays` (returned as
            given by :meth:`batch_arrays`).
        result_fn : callable, optional
            ``result_fn(seq, position) -> dict``: the batch's first response,
            stored in the same transaction (a retry with the key gets it).

        Returns
        -------
        (seq, position) : (int, int)

        Raises
        ------
        flatserve.service.status.FieldNotFoundError
            The field was deleted.
        KeyTakenError
            ``idem_key`` is already stored for this field (nothing is stored).
        flatserve.service.status.StorageFullError
            Out of space (nothing is stored).
        """

    @abc.abstractmethod
    def set_result(self, field_id: int, seq: int, result: dict, *, replace: bool = True,
                   durable: bool = False) -> None:
        """Store (``replace``: or overwrite) the response of batch ``seq``.

        ``durable=False`` may skip the fsync (a later commit makes it durable; a
        crash may lose it, and a retry then recomputes it). ``replace=False``
        keeps a response already stored. A deleted field or batch: no-op.
        """

    # -- reads ---------------------------------------------------------------------
    @abc.abstractmethod
    def state(self) -> tuple[int, list[FieldRow]]:
        """The log head and the stored fields, read in ONE consistent view.

        Returns
        -------
        (position, fields) : (int, list of FieldRow)
            Every entry up to ``position`` is reflected in ``fields`` (ordered by
            id) and no later one; a replica restores these fields to
            ``position`` and follows the log from there.
        """

    @abc.abstractmethod
    def field(self, field_id: int) -> FieldRow:
        """One stored field (current state).

        Raises
        ------
        flatserve.service.status.FieldNotFoundError
        """

    @abc.abstractmethod
    def find_batch(self, field_id: int, idem_key: str) -> BatchRow | None:
        """The field's batch stored with this idempotency key, or None."""

    @abc.abstractmethod
    def batches(self, field_id: int, after_seq: int = 0,
                upto_position: int | None = None) -> list[BatchRow]:
        """The field's batches with ``seq > after_seq`` (and ``position <=
        upto_position`` if given), in seq order."""

    @abc.abstractmethod
    def batch_arrays(self, field_id: int, seq: int) -> dict[str, np.ndarray]:
        """The stored arrays of one batch (read-only views are fine).

        Raises
        ------
        flatserve.service.status.FieldNotFoundError
            No such batch (the field was deleted meanwhile).
        """

    @abc.abstractmethod
    def batch_stats(self, field_id: int) -> tuple[int, int, int, int]:
        """``(number of batches, rows, bytes of stored arrays, last seq)``."""

    # -- the log -------------------------------------------------------------------------
    @abc.abstractmethod
    def head(self) -> int:
        """The position of the last committed entry (0: empty log)."""

    @abc.abstractmethod
    def read_log(self, after: int, limit: int = 256) -> list[LogEntry]:
        """Up to ``limit`` committed entries with ``position > after``, in position
        order (see the module doc: no entry below one returned can appear later)."""

    @abc.abstractmethod
    def wait_for_change(self, timeout: float) -> None:
        """Block until the log may have grown since this method last returned, or
        ``timeout`` seconds passed. Spurious returns are allowed; missed changes
        are not. A commit by this process (any thread) returns it at once; a
        commit by another process within a few milliseconds (SQLite: ``PRAGMA
        data_version`` polled; PostgreSQL: LISTEN/NOTIFY). Called by one thread."""

    @abc.abstractmethod
    def wake(self) -> None:
        """Make the current (or next) :meth:`wait_for_change` return at once."""

    # -- snapshots -------------------------------------------------------------------------
    @abc.abstractmethod
    def write_snapshot(self, field_id: int, seq: int, position: int,
                       save: Callable[[Path], None],
                       check: Callable[[], None] | None = None) -> SnapshotInfo:
        """Store a snapshot of a field holding its batches ``1..seq`` (the last at
        log ``position``) and announce it: the field's row points at it and a
        ``snapshot`` entry is appended, in one transaction, only once the data is
        durable. The previous snapshot is removed after the commit.

        Parameters
        ----------
        field_id, seq, position : int
        save : callable
            ``save(path, stage)`` writes the snapshot to a local file ``path``
            (it may append an extension: the one file it creates is taken) and
            the parts it names that are not stored yet to the local directory
            ``stage`` (``<stage>/<key>``; see
            :meth:`flatserve.contract.SampledField.write_parts`); it returns
            the keys of every part the snapshot names (None or []: none). The
            parts are the field's: stored with the snapshot, each once
            whatever the number of snapshots naming it, removed once no
            snapshot of the field names them.
        check : callable, optional
            Called once the data is stored, just before the field is pointed at
            it; an exception it raises abandons the snapshot (its data is
            removed) and is raised (the writer's lease was lost: another
            replica's clean-up may be removing what is not pointed at).

        Returns
        -------
        SnapshotInfo
            With the ``snapshot`` entry's position.

        Raises
        ------
        flatserve.service.status.FieldNotFoundError
            The field was deleted (nothing is kept).
        flatserve.service.status.StorageFullError
        """

    @abc.abstractmethod
    def load_snapshot(self, row: FieldRow, load: Callable[[Path, Callable[[str], bytes]], T]) -> T:
        """``load(path, parts)`` of a local file holding the row's snapshot; its
        result. ``parts(key)`` gives the bytes of a part the snapshot names
        (:meth:`read_part`, read when asked for).

        Raises
        ------
        SnapshotGoneError
            The snapshot was replaced and removed since ``row`` was read.
        Exception
            Whatever ``load`` raises (a damaged snapshot: the caller rebuilds
            from the batches).
        """

    def snapshot_location(self, row: FieldRow) -> str:
        """Where the row's snapshot is, for messages (a path, a large object id)."""
        return str(row.snapshot_file)

    @abc.abstractmethod
    def snapshot_bytes(self, row: "FieldRow | str | None") -> int:
        """Size of the row's snapshot, given the row or its ``snapshot_file``
        (0: none or gone)."""

    @abc.abstractmethod
    def read_part(self, field_id: int, key: str) -> bytes:
        """The bytes of snapshot part ``key`` of field ``field_id``, unchecked (the
        caller checks them against their key): what ``load_snapshot``'s ``parts``
        gives, and what a process holding a field's tile reads for itself.

        Raises
        ------
        flatserve.errors.SnapshotError
            No such part: damaged, or the snapshot naming it was replaced
            meanwhile (``load_snapshot`` tells the two apart).
        flatserve.service.status.StorageError
        """

    def load_with_parts(self, row: FieldRow, path: Path,
                        load: Callable[[Path, Callable[[str], bytes]], T]) -> T:
        """``load(path, parts)`` of the row's staged (or local) snapshot file, its
        parts read when asked for (:meth:`read_part`): the one place both
        backends' ``load_snapshot`` tell a replaced snapshot from a damaged one.

        Raises
        ------
        SnapshotGoneError
            ``load`` failed (a part, or the file, gone) while the field points at
            another snapshot now (or is gone): it was replaced while it was read.
        Exception
            Otherwise whatever ``load`` raises.
        """
        from ..status import FieldNotFoundError, StorageError

        try:
            return load(path, lambda key: self.read_part(row.id, key))
        except (SnapshotGoneError, StorageError):
            raise
        except Exception:
            try:
                replaced = self.field(row.id).snapshot_file != row.snapshot_file
            except FieldNotFoundError:
                replaced = True
            if replaced:
                raise SnapshotGoneError(f"snapshot {row.snapshot_file} of field id {row.id} "
                                        "was replaced") from None
            raise

    @abc.abstractmethod
    def snapshot_parts(self, field_id: int) -> set[str]:
        """Keys of the snapshot parts stored for field ``field_id`` (a snapshot
        writer passes them to ``write_parts`` as known: not written again).
        Stable while the caller holds the field's :func:`snapshot_lease`."""

    @abc.abstractmethod
    def store_part(self, field_id: int, key: str, data: bytes) -> int:
        """Store one snapshot part of field ``field_id`` ahead of the snapshot
        that will name it, durably on return: for a process that holds some of
        a field's shards and serialises them itself, so that the parts never
        travel through the snapshot's writer (who then names them among the
        keys ``save`` returns to :meth:`write_snapshot`). A part stored already
        is kept as it is. The caller acts for a writer holding the field's
        :func:`snapshot_lease`; a part no snapshot comes to name is removed by
        the field's next snapshot.

        Returns
        -------
        int
            Bytes written (0: the part was there).
        """

    @abc.abstractmethod
    def remove_parts(self, field_id: int, keys: Sequence[str]) -> None:
        """Remove these parts of field ``field_id`` (stored for a snapshot that was
        abandoned, which no snapshot names). The caller holds the field's
        :func:`snapshot_lease`."""

    @abc.abstractmethod
    def acquire_lease(self, name: str, owner: str, ttl: float) -> bool:
        """Take (or renew) the lease ``name`` for ``owner`` for ``ttl`` seconds:
        True if ``owner`` holds it now, False if another owner holds an
        unexpired one. Used for :func:`snapshot_lease` (one snapshot writer of a
        field at a time, across replicas); a writer killed holding it blocks
        others until it expires. Leases of different names are independent.
        Owners are :func:`lease_owner`'s ``"<hostname>:<pid>:<random>"``: a
        backend may take over at once a lease whose owner is a dead process of
        this host (the SQLite backend does)."""

    @abc.abstractmethod
    def renew_lease(self, name: str, owner: str, ttl: float) -> bool:
        """Extend the lease ``name`` that ``owner`` holds without a break: False if
        it lapsed meanwhile (expired, taken by another owner, its session gone),
        even if it is free now. Never takes it anew (a lapse may have let another
        replica's clean-up remove what ``owner`` was writing under it)."""

    @abc.abstractmethod
    def release_lease(self, name: str, owner: str) -> None:
        """Give the lease up if ``owner`` holds it."""

    def clean_orphans(self) -> int:
        """Remove snapshot data no field points at (left by a writer that died);
        the number removed. Safe while other writers run: the data of fields
        that are gone (and what belongs to no field) goes at once, since no
        writer can point a deleted field at anything; a live field's only under
        its :func:`snapshot_lease`, taken here field by field under an owner of
        its own (:data:`CLEAN_LEASE_S`): a field whose lease a writer holds is
        left for the next clean-up.

        Raises
        ------
        flatserve.service.status.StorageError
        """
        n = self._clean_orphans(None)
        owner = lease_owner("clean-")
        for field_id in sorted(self._orphan_fields()):
            name = snapshot_lease(field_id)
            if not self.acquire_lease(name, owner, CLEAN_LEASE_S):
                continue
            try:
                n += self._clean_orphans(field_id)
            finally:
                self.release_lease(name, owner)
        return n

    @abc.abstractmethod
    def _orphan_fields(self) -> set[int]:
        """Ids of the stored fields that have snapshot data they do not point at
        (a hint: :meth:`_clean_orphans` checks again under the field's lease)."""

    @abc.abstractmethod
    def _clean_orphans(self, field_id: int | None) -> int:
        """Remove the snapshot data field ``field_id`` does not point at (the
        caller holds its :func:`snapshot_lease`; its parts stay: its next
        snapshot removes those no snapshot names); None: the data of fields that
        are gone and what belongs to no field. The number removed."""


#: backend class by URL scheme: "module:Class" (imported on first use, so a
#: backend's driver is needed only where it is used)
BACKENDS: dict[str, str] = {
    "sqlite": "flatserve.service.log.storage:SQLiteBackend",
    "postgresql": "flatserve.service.log.pgstorage:PostgresBackend",
    "postgres": "flatserve.service.log.pgstorage:PostgresBackend",
}


def backend_class(url: str | None) -> type[LogBackend]:
    """The class for ``database_url`` (None: SQLite in the data directory)."""
    scheme = "sqlite" if not url else url.split(":", 1)[0].lower()
    target = BACKENDS.get(scheme)
    if target is None:
        from ..status import StorageError

        raise StorageError(f"database_url: unknown scheme {scheme!r} (known: "
                           f"{', '.join(sorted(BACKENDS))})")
    mod, cls = target.split(":")
    return getattr(importlib.import_module(mod), cls)


def open_backend(settings, *, follower: bool = False) -> LogBackend:
    """The backend of a server's settings: ``settings.database_url`` set →
    that database (the class's ``from_settings``); else SQLite in
    ``settings.data_dir``. Each backend class has a classmethod
    ``from_settings(settings, *, follower=False) -> LogBackend``.

    ``follower``: for a process that only reads the log and stores snapshot
    parts (a shard worker of a cluster): SQLite then takes no lock on the data
    directory (the server holding it does) and refuses writes to the database."""
    return backend_class(settings.database_url).from_settings(settings, follower=follower)
