"""The storage room's rulebook: the domain rules of the SQL backends, written once.

:class:`SQLBackend` implements the parts of
:class:`~flatserve.service.log.backend.LogBackend` that are the same for every SQL
database: how batches are numbered, the idempotency check, deleting a field,
pointing a field at its snapshot, the column lists and the mapping of rows to
:class:`~.rows.FieldRow`,
:class:`~.rows.BatchRow` and
:class:`~.rows.LogEntry`, and the mapping of failures to the
service's errors (:func:`storage_failure`). What differs between databases is a
small :class:`Dialect` (placeholders, row locks, the legacy column of SQLite)
and a few hooks each backend implements (``_write``, ``_read``, ``_append`` and
the snapshot hooks); the backends keep what truly differs: connections, how
snapshots travel, leases and change notification.

The rules
---------
* **Batch numbers.** A batch's ``seq`` is the field's largest stored seq plus
  one, and above its ``snapshot_seq`` (batches folded into a snapshot and then
  removed are never numbered again); drawn inside the write transaction, after
  the field's row is locked.
* **Idempotency.** A batch whose key the field already stores is refused inside
  that transaction with :class:`~.rows.KeyTakenError`
  carrying the stored batch (nothing is written).
* **Pointing a field at a snapshot** happens in one transaction that refuses a
  deleted field (:class:`~flatserve.service.status.FieldNotFoundError`) and data
  that is gone (a clean-up under a lease the writer lost), and appends the
  ``snapshot`` entry; a failure removes the new data unless the field points at
  it (a commit whose reply was lost keeps it); the replaced snapshot is removed
  after the commit.
"""
from __future__ import annotations

import abc
import enum
import errno
import json
import time
from dataclasses import dataclass
from typing import Callable, TypeVar

import numpy as np

from .backend import LogBackend
from .rows import BatchRow, FieldRow, KeyTakenError, LogEntry
from .blobs import pack_arrays, unpack_arrays
from ..status import (FieldExistsError, FieldNotFoundError, StorageError, StorageFullError,
                     StorageUnavailableError)

T = TypeVar("T")


class Failure(enum.Enum):
    """What a database error means for the service (a backend classifies its
    driver's errors; :func:`storage_failure` words them)."""

    FULL = "full"                # out of space: a 507, nothing stored
    DAMAGED = "damaged"          # the stored data is damaged: restore or move it away
    UNREACHABLE = "unreachable"  # the database cannot be reached: a 503 to retry
    FAILED = "failed"            # anything else


#: what a client is told of each failure (:attr:`StorageError.public`): the database's
#: own message and where it is (a path, a host, a user, relation files) go to the log
PUBLIC_FAILURE = {
    Failure.FULL: "storage is out of space: nothing was stored; retry once space is freed "
                  "(the server's log says where)",
    Failure.DAMAGED: "storage failed: the database is damaged (the server's log says where)",
    Failure.UNREACHABLE: "the database cannot be reached; retry (a write in flight may be "
                         "stored: retry it with its Idempotency-Key)",
    Failure.FAILED: "storage failed (the server's log has the database's message)",
}


def storage_failure(kind: Failure, exc: BaseException, where: str) -> StorageError:
    """The service's error for a database failure of ``kind`` at ``where`` (a path,
    or a URL without its password). Its text names ``where`` and the database's
    message (for the log and the start-up line); its ``public`` text, which a client
    gets, names neither."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    if kind is Failure.FULL:
        err = StorageFullError(f"storage failed: {where} is out of space ({msg})")
    elif kind is Failure.DAMAGED:
        err = StorageError(f"storage failed: the database {where} is damaged ({msg}); "
                           "restore it from a backup or move it away")
    elif kind is Failure.UNREACHABLE:
        err = StorageUnavailableError(f"the database {where} cannot be reached ({msg}); "
                                      "retry (a write in flight may be stored: retry it "
                                      "with its Idempotency-Key)")
    else:
        err = StorageError(f"storage failed ({where}): {msg}")
    err.public = PUBLIC_FAILURE[kind]
    return err


def snapshot_failure(exc: OSError) -> StorageError:
    """The error for a snapshot's local file that could not be written or staged
    (out of space or quota: :class:`StorageFullError`, a 507)."""
    full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
    return (StorageFullError if full else StorageError)(f"snapshot failed: {exc}")


def snapshot_name(row: "FieldRow | str | None") -> str | None:
    """The snapshot a :meth:`LogBackend.snapshot_bytes` argument names."""
    return row if isinstance(row, (str, type(None))) else row.snapshot_file


@dataclass(frozen=True)
class Dialect:
    """What a SQL database spells differently.

    Statements of the rulebook are written with ``?`` for a parameter and
    ``?b`` for a binary one (a blob); :meth:`sql` turns them into the driver's.

    Attributes
    ----------
    name : str
        The key of :data:`flatserve.service.log.sqlschema.TYPES`.
    param, blob_param : str
        The driver's placeholders.
    for_update, for_share : str
        Row locks appended to a ``SELECT`` (empty where a write transaction
        locks the whole database).
    legacy_result : bool
        ``batches.result`` exists (SQLite's schema 2): written as ``'null'``,
        read when ``batch_results`` has no row.
    arrays_before_position : bool
        The batch row (its arrays: the slow part) is written before the
        position is drawn (a backend whose position lock serialises
        concurrent writers holds it only for the small statements after).
    taken : tuple of exception classes
        Driver errors of a UNIQUE constraint (:meth:`SQLBackend.create_field`:
        the name is taken).
    gone : tuple of exception classes
        Driver errors of :meth:`SQLBackend.set_result` that mean the batch was
        deleted meanwhile (a no-op).
    """

    name: str
    param: str
    blob_param: str
    for_update: str = ""
    for_share: str = ""
    legacy_result: bool = False
    arrays_before_position: bool = False
    taken: tuple[type[BaseException], ...] = ()
    gone: tuple[type[BaseException], ...] = ()

    def sql(self, text: str) -> str:
        """``text`` with the driver's placeholders."""
        return text.replace("?b", "\0").replace("?", self.param).replace("\0", self.blob_param)


class SQLBackend(LogBackend):
    """The rules of :mod:`.sqlrules` over one SQL database (see the module doc).

    A subclass sets :attr:`dialect` and implements the hooks: :meth:`_write`,
    :meth:`_read`, :meth:`_append` and the snapshot hooks
    (:meth:`_forget_snapshot`, :meth:`_snapshot_stored`,
    :meth:`_discard_snapshots`, :meth:`_parts_stored`, :meth:`_discard_parts`).
    """

    dialect: Dialect

    # -- hooks --------------------------------------------------------------------
    @abc.abstractmethod
    def _write(self, fn: Callable[[object], T], *, appends: bool = True,
               durable: bool = True) -> T:
        """``fn(conn)`` in one write transaction, committed (fsync'd unless not
        ``durable``); ``appends``: it appended to the log (this process's follower
        is woken after the commit). Database errors are raised as
        :class:`StorageError` (their ``__cause__`` the driver's)."""

    @abc.abstractmethod
    def _read(self, fn: Callable[[object], T], *, consistent: bool = False) -> T:
        """``fn(conn)`` on a reading connection (``consistent``: in one read
        transaction, one view of the database)."""

    @abc.abstractmethod
    def _append(self, conn, kind: str, field_id: int, seq: int = 0, nrows: int = 0) -> int:
        """Append a log entry in the caller's transaction; its position (drawn so
        that positions are in commit order: see :mod:`.backend`)."""

    def _rows(self, conn, sql: str, args: tuple = (), *, binary: bool = False) -> list:
        """The rows of a rulebook statement (``binary``: it returns blobs)."""
        return conn.execute(self.dialect.sql(sql), args).fetchall()

    def _run_sql(self, conn, sql: str, args: tuple = ()) -> int:
        """Execute a rulebook statement; the number of rows it changed."""
        return conn.execute(self.dialect.sql(sql), args).rowcount

    @abc.abstractmethod
    def _forget_snapshot(self, conn, field_id: int, name: str | None) -> list[str]:
        """In the transaction deleting field ``field_id`` (snapshot ``name``):
        remove its snapshot data now, or return what to remove after the commit."""

    @abc.abstractmethod
    def _snapshot_stored(self, conn, name: str) -> bool:
        """In the pointing transaction: whether snapshot ``name``'s data is still
        stored (and kept so until the commit)."""

    @abc.abstractmethod
    def _discard_snapshots(self, names: list[str]) -> None:
        """Remove snapshots' data, best effort (clean_orphans removes the rest)."""

    @abc.abstractmethod
    def _parts_stored(self, conn, field_id: int, keys: list[str]) -> bool:
        """In the pointing transaction: whether every part ``keys`` of field
        ``field_id`` is still stored (and kept so until the commit)."""

    @abc.abstractmethod
    def _discard_parts(self, field_id: int, keep: list[str]) -> None:
        """Remove the parts of field ``field_id`` that are not in ``keep`` (the
        snapshot it now points at names those; none once it is deleted), best
        effort: the field's next snapshot, or ``clean_orphans`` for a field that
        is gone, removes what is left."""

    # -- rows -----------------------------------------------------------------------
    _FIELD_COLS = ("SELECT id, name, spec, basis, created, position, snapshot_file, snapshot_seq,"
                   " snapshot_position FROM fields ")

    @staticmethod
    def _field_row(r) -> FieldRow:
        return FieldRow(int(r[0]), r[1], json.loads(r[2]), unpack_arrays(bytes(r[3])),
                        float(r[4]), int(r[5]), r[6], int(r[7]), int(r[8]))

    @property
    def _batch_cols(self) -> str:
        result = "COALESCE(r.result, b.result)" if self.dialect.legacy_result else "r.result"
        return ("SELECT b.seq, b.position, b.idem_key, b.content_hash, b.form, b.nrows, "
                f"{result} FROM batches b"
                " LEFT JOIN batch_results r ON r.field_id=b.field_id AND r.seq=b.seq ")

    @staticmethod
    def _batch_row(r) -> BatchRow:
        return BatchRow(int(r[0]), int(r[1]), r[2], r[3], r[4], int(r[5]),
                        None if r[6] is None else json.loads(r[6]))

    @staticmethod
    def _log_entry(r) -> LogEntry:
        return LogEntry(int(r[0]), r[1], int(r[2]), int(r[3]), float(r[4]), int(r[5]))

    def _one(self, conn, sql: str, args: tuple = (), *, binary: bool = False):
        rows = self._rows(conn, sql, args, binary=binary)
        return rows[0] if rows else None

    def _lock_field(self, conn, field_id: int, column: str):
        """A write to a field locks its row first (the same lock order everywhere:
        the field's row, then the log's position); ``column``'s value.

        Raises
        ------
        FieldNotFoundError
            The field is not stored (deleted meanwhile).
        """
        row = self._one(conn, f"SELECT {column} FROM fields WHERE id=?" + self.dialect.for_update,
                        (field_id,))
        if row is None:
            raise FieldNotFoundError(f"field id {field_id} is not stored (deleted meanwhile?)")
        return row[0]

    # -- fields -----------------------------------------------------------------------
    def create_field(self, name: str, spec: dict, basis: dict[str, np.ndarray]) -> tuple[int, int]:
        blob = pack_arrays(basis)

        def fn(conn):
            try:
                self._run_sql(conn, "INSERT INTO fields(name, spec, basis, created)"
                                    " VALUES (?, ?, ?b, ?)",
                              (name, json.dumps(spec), blob, time.time()))
            except self.dialect.taken:
                raise FieldExistsError(f"field {name!r} already exists") from None
            fid = int(self._one(conn, "SELECT id FROM fields WHERE name=?", (name,))[0])
            pos = self._append(conn, "create", fid)
            self._run_sql(conn, "UPDATE fields SET position=? WHERE id=?", (pos, fid))
            return fid, pos

        return self._write(fn)

    def delete_field(self, field_id: int) -> int:
        later: list[str] = []

        def fn(conn):
            snap = self._lock_field(conn, field_id, "snapshot_file")
            self._run_sql(conn, "DELETE FROM batch_results WHERE field_id=?", (field_id,))
            self._run_sql(conn, "DELETE FROM batches WHERE field_id=?", (field_id,))
            later[:] = self._forget_snapshot(conn, field_id, snap)
            self._run_sql(conn, "DELETE FROM fields WHERE id=?", (field_id,))
            return self._append(conn, "delete", field_id)

        pos = self._write(fn)
        self._discard_snapshots(later)
        self._discard_parts(field_id, [])  # every part of the field (none kept)
        return pos

    def state(self) -> tuple[int, list[FieldRow]]:
        def fn(conn):
            head = self._one(conn, "SELECT COALESCE(MAX(position), 0) FROM log")[0]
            return int(head), self._rows(conn, self._FIELD_COLS + "ORDER BY id", binary=True)

        head, rows = self._read(fn, consistent=True)
        return head, [self._field_row(r) for r in rows]

    def fields(self) -> list[FieldRow]:
        return self.state()[1]

    def field(self, field_id: int) -> FieldRow:
        r = self._read(lambda c: self._one(c, self._FIELD_COLS + "WHERE id=?", (field_id,),
                                           binary=True))
        if r is None:
            raise FieldNotFoundError(f"field id {field_id} is not stored")
        return self._field_row(r)

    # -- batches ------------------------------------------------------------------------
    def find_batch(self, field_id: int, idem_key: str) -> BatchRow | None:
        r = self._read(lambda c: self._one(
            c, self._batch_cols + "WHERE b.field_id=? AND b.idem_key=?", (field_id, idem_key)))
        return None if r is None else self._batch_row(r)

    def add_batch(self, field_id: int, *, idem_key: str | None, chash: str, form: str,
                  nrows: int, blob: bytes,
                  result_fn: Callable[[int, int], dict] | None = None) -> tuple[int, int]:
        d = self.dialect
        cols = "field_id, seq, idem_key, content_hash, form, nrows, arrays, created, position"
        vals = "?, ?, ?, ?, ?, ?, ?b, ?, ?"
        if d.legacy_result:
            cols, vals = cols + ", result", vals + ", 'null'"
        insert = f"INSERT INTO batches({cols}) VALUES ({vals})"

        def fn(conn):
            snap_seq = self._lock_field(conn, field_id, "snapshot_seq")
            if idem_key is not None:
                r = self._one(conn, self._batch_cols + "WHERE b.field_id=? AND b.idem_key=?",
                              (field_id, idem_key))
                if r is not None:
                    raise KeyTakenError(self._batch_row(r))
            last = self._one(conn, "SELECT COALESCE(MAX(seq), 0) FROM batches WHERE field_id=?",
                             (field_id,))[0]
            seq = max(int(last), int(snap_seq)) + 1
            args = (field_id, seq, idem_key, chash, form, nrows, blob, time.time())
            if d.arrays_before_position:
                self._run_sql(conn, insert, args + (0,))
                pos = self._append(conn, "batch", field_id, seq, nrows)
                self._run_sql(conn, "UPDATE batches SET position=? WHERE field_id=? AND seq=?",
                              (pos, field_id, seq))
            else:
                pos = self._append(conn, "batch", field_id, seq, nrows)
                self._run_sql(conn, insert, args + (pos,))
            if result_fn is not None:  # in batch_results, where set_result writes too
                self._run_sql(conn, "INSERT INTO batch_results(field_id, seq, result)"
                                    " VALUES (?, ?, ?)",
                              (field_id, seq, json.dumps(result_fn(seq, pos))))
            return seq, pos

        return self._write(fn)

    def set_result(self, field_id: int, seq: int, result: dict, *, replace: bool = True,
                   durable: bool = False) -> None:
        action = "UPDATE SET result=excluded.result" if replace else "NOTHING"
        sql = ("INSERT INTO batch_results(field_id, seq, result) SELECT ?, ?, ?"
               " WHERE EXISTS (SELECT 1 FROM batches WHERE field_id=? AND seq=?)"
               f" ON CONFLICT (field_id, seq) DO {action}")
        try:
            self._write(lambda c: self._run_sql(c, sql, (field_id, seq, json.dumps(result),
                                                         field_id, seq)),
                        appends=False, durable=durable)
        except StorageError as exc:
            if isinstance(exc.__cause__, self.dialect.gone):
                return  # the batch was deleted meanwhile
            raise

    def batches(self, field_id: int, after_seq: int = 0,
                upto_position: int | None = None) -> list[BatchRow]:
        upto = (1 << 62) if upto_position is None else int(upto_position)
        rows = self._read(lambda c: self._rows(
            c, self._batch_cols + "WHERE b.field_id=? AND b.seq>? AND b.position<=?"
            " ORDER BY b.seq", (field_id, after_seq, upto)))
        return [self._batch_row(r) for r in rows]

    def batch_arrays(self, field_id: int, seq: int) -> dict[str, np.ndarray]:
        r = self._read(lambda c: self._one(
            c, "SELECT arrays FROM batches WHERE field_id=? AND seq=?", (field_id, seq),
            binary=True))
        if r is None:
            raise FieldNotFoundError(f"field id {field_id} has no batch {seq}")
        return unpack_arrays(r[0])

    def batch_stats(self, field_id: int) -> tuple[int, int, int, int]:
        r = self._read(lambda c: self._one(
            c, "SELECT COUNT(*), COALESCE(SUM(nrows), 0), COALESCE(SUM(LENGTH(arrays)), 0),"
            " COALESCE(MAX(seq), 0) FROM batches WHERE field_id=?", (field_id,)))
        return int(r[0]), int(r[1]), int(r[2]), int(r[3])

    # -- the log ------------------------------------------------------------------------
    def head(self) -> int:
        return int(self._read(lambda c: self._one(
            c, "SELECT COALESCE(MAX(position), 0) FROM log"))[0])

    def read_log(self, after: int, limit: int = 256) -> list[LogEntry]:
        rows = self._read(lambda c: self._rows(
            c, "SELECT position, kind, field_id, seq, committed, nrows FROM log"
            " WHERE position>? ORDER BY position LIMIT ?", (after, limit)))
        return [self._log_entry(r) for r in rows]

    # -- snapshots ----------------------------------------------------------------------
    def _point(self, field_id: int, name: str, seq: int, position: int,
               check: Callable[[], None] | None, parts: list[str] = ()) -> int:
        """Point the field at snapshot ``name`` (stored and durable, with the
        ``parts`` it names) and announce it: the rule of the module doc. The
        ``snapshot`` entry's position. Then the former snapshot and the parts no
        longer named are removed."""
        old: list[str] = []
        parts = list(parts)

        def fn(conn):
            now = self._lock_field(conn, field_id, "snapshot_file")
            if not self._snapshot_stored(conn, name):  # a clean-up under a lease we lost
                raise StorageError(f"snapshot {name} was removed before the field pointed at it")
            if parts and not self._parts_stored(conn, field_id, parts):
                raise StorageError(f"a part of snapshot {name} was removed before the field "
                                   "pointed at it")
            old[:] = [now] if now and now != name else []
            self._run_sql(conn, "UPDATE fields SET snapshot_file=?, snapshot_seq=?,"
                                " snapshot_position=? WHERE id=?",
                          (name, seq, position, field_id))
            return self._append(conn, "snapshot", field_id, seq)

        try:
            if check is not None:
                check()
            pos = self._write(fn)
        except BaseException:
            if not self._points_at(field_id, name):  # (a commit whose reply was lost: keep)
                self._discard_snapshots([name])
            raise
        self._discard_snapshots(old)  # first: a reader of the former one is told it is gone
        self._discard_parts(field_id, parts)
        return pos

    def _points_at(self, field_id: int, name: str) -> bool:
        """Whether the field points at snapshot ``name`` (True when it cannot be
        told: what no field points at is removed by clean_orphans later)."""
        try:
            r = self._read(lambda c: self._one(c, "SELECT snapshot_file FROM fields WHERE id=?",
                                               (field_id,)))
        except (StorageError, OSError):
            return True
        return r is not None and r[0] == name
