"""The SQLite backend of the log (:class:`flatserve.service.backend.LogBackend`):
SQLite (WAL, ``synchronous=FULL``) plus snapshot files, in the data directory.

Layout of ``data_dir``::

    flatserve.sqlite3            fields, batches, batch_results, log, leases
    flatserve.lock               held (flock) by the server or replica group using it
    snapshots/f<id>-s<seq>.snap  Field.save() (AtlasField.save()) of field <id> after batch <seq>

A batch row holds the raw input arrays (one blob, :mod:`.blobs`), its form
(``rays``, ``parametric`` or ``flats``), the idempotency key, a hash of the
content and its log position; its response (for idempotent retries) is in
``batch_results``, written in the batch's own transaction and completed once a
``wait=true`` batch is applied. Every change appends one row to ``log`` in its
own transaction: SQLite has one writer at a time, so the ``AUTOINCREMENT``
position drawn inside the write transaction is in commit order. A batch is
acknowledged only after its transaction has committed (fsync'd by SQLite).
Snapshots are written to a temporary file, fsync'd, renamed into place and the
directory fsync'd; only then does the database point at them (and the log
announce them).

Several processes may use one database: the replicas of one ``flatserve serve
--processes N``, which share the data directory's lock (an inherited open file,
``lock_fd``). Any other server finds the lock taken and refuses to start
(:class:`~flatserve.service.status.DataDirInUseError`).

Schema versions: 2 (fields, batches, batch_results) is migrated on open to 3
(adds the log, backfilled field by field in creation and batch order, the
positions of fields, batches and snapshots, and the leases).
"""
from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
import sqlite3
import threading
import time
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

from .backend import (BatchRow, FieldRow, KeyTakenError, LogBackend, LogEntry, SnapshotGoneError,
                      SnapshotInfo)
from .blobs import pack_arrays, unpack_arrays
from .status import DataDirInUseError, FieldExistsError, FieldNotFoundError, StorageError, StorageFullError

log = logging.getLogger("flatserve.service.storage")

T = TypeVar("T")

SCHEMA_VERSION = 3
DB_NAME = "flatserve.sqlite3"
#: seconds a writer waits for another process's write transaction
BUSY_TIMEOUT_S = 60.0

_SCHEMA_V2 = """
CREATE TABLE IF NOT EXISTS fields (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    name TEXT NOT NULL UNIQUE,
    spec TEXT NOT NULL,
    basis BLOB NOT NULL,
    created REAL NOT NULL,
    snapshot_file TEXT,
    snapshot_seq INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS batches (
    field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    idem_key TEXT,
    content_hash TEXT NOT NULL,
    form TEXT NOT NULL,
    nrows INTEGER NOT NULL,
    arrays BLOB NOT NULL,
    result TEXT NOT NULL,
    created REAL NOT NULL,
    PRIMARY KEY (field_id, seq)
);
CREATE UNIQUE INDEX IF NOT EXISTS batches_idem ON batches(field_id, idem_key)
    WHERE idem_key IS NOT NULL;
-- responses written after their batch's commit (batches.result is then 'null'):
-- kept apart so that writing one does not rewrite the batch's arrays
CREATE TABLE IF NOT EXISTS batch_results (
    field_id INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    result TEXT NOT NULL,
    PRIMARY KEY (field_id, seq)
);
"""

#: version 2 -> 3 (run in one transaction)
_MIGRATE_V3 = """
ALTER TABLE fields ADD COLUMN position INTEGER NOT NULL DEFAULT 0;
ALTER TABLE fields ADD COLUMN snapshot_position INTEGER NOT NULL DEFAULT 0;
ALTER TABLE batches ADD COLUMN position INTEGER NOT NULL DEFAULT 0;
-- the log of field operations; no foreign key: a delete outlives its field
CREATE TABLE log (
    position INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    field_id INTEGER NOT NULL,
    seq INTEGER NOT NULL DEFAULT 0,
    nrows INTEGER NOT NULL DEFAULT 0,
    committed REAL NOT NULL
);
CREATE TABLE leases (
    name TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    expires REAL NOT NULL
);
"""

LOCK_NAME = "flatserve.lock"


def _lock_data_dir(data_dir: Path, lock_fd: int | None = None):
    """Hold an exclusive lock on the data directory for this process's lifetime
    (released by :meth:`SQLiteBackend.close` or when the process dies, kill -9
    included). A second server on the same directory would diverge from the
    first: refused. ``lock_fd``: an inherited descriptor of the lock file whose
    lock the parent (``serve --processes N``) holds for the replica group."""
    path = data_dir / LOCK_NAME
    if lock_fd is not None:
        try:
            mine, theirs = os.fstat(lock_fd), os.stat(path)
            if (mine.st_dev, mine.st_ino) != (theirs.st_dev, theirs.st_ino):
                raise StorageError(f"lock_fd {lock_fd} is not {path}")
            fh = os.fdopen(os.dup(lock_fd), "a+")
            # the same open file description as the holder's: a no-op if it holds it
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            raise StorageError(f"lock_fd {lock_fd}: not the lock of {data_dir} ({exc})") from exc
        return fh
    try:
        fh = open(path, "a+")
    except OSError as exc:
        raise StorageError(f"cannot open {path}: {exc}") from exc
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "unknown"
        fh.close()
        raise DataDirInUseError(
            f"the data directory {data_dir} is in use by another flatserve server (pid "
            f"{holder}); stop it, or give this one another --data-dir") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    return fh


def lock_data_dir(data_dir: Path | str) -> int:
    """Take the data directory's lock for a replica group; the descriptor to pass
    to its processes (``lock_fd``; inheritable). Raises
    :class:`~flatserve.service.status.DataDirInUseError` as a server would."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    fh = _lock_data_dir(data_dir)
    fd = os.dup(fh.fileno())
    fh.close()  # the dup keeps the open file description (and its lock)
    os.set_inheritable(fd, True)
    return fd


def storage_error(exc: sqlite3.Error, db_path: Path | None = None) -> StorageError:
    """The :class:`StorageError` for a database error (:class:`StorageFullError` when
    the disk is full); a damaged database is named (``db_path``)."""
    code = getattr(exc, "sqlite_errorcode", None)
    full = code == sqlite3.SQLITE_FULL or "disk is full" in str(exc)
    if not full and db_path is not None and (
            code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
            or "malformed" in str(exc) or "not a database" in str(exc)):
        return StorageError(f"storage failed: the database {db_path} is damaged ({exc}); "
                            "restore it from a backup or move it away")
    return (StorageFullError if full else StorageError)(f"storage failed: {exc}")


def _owner_dead(owner: str) -> bool:
    """A lease owner ``host:pid:...`` that is a process of this machine no longer
    running (its lease is taken over at once instead of when it expires)."""
    host, _, rest = owner.partition(":")
    pid = rest.partition(":")[0]
    if host != socket.gethostname() or not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except OSError:  # alive (another user's)
        return False
    return False


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _run_script(db: sqlite3.Connection, script: str) -> None:
    """Run the statements of ``script`` one by one inside the caller's transaction
    (``executescript`` would commit it first)."""
    script = "\n".join(ln for ln in script.splitlines() if not ln.strip().startswith("--"))
    for sql in script.split(";"):
        if sql.strip():
            db.execute(sql)


def _migrate(db: sqlite3.Connection) -> None:
    """Schema 2 -> 3 inside the caller's write transaction: the log is backfilled
    field by field (ids in creation order), each field's ``create`` then its
    batches in seq order; snapshots get the position of their last batch."""
    _run_script(db, _MIGRATE_V3)
    fields = db.execute("SELECT id, created, snapshot_seq FROM fields ORDER BY id").fetchall()
    nb = 0
    for fid, created, snap_seq in fields:
        pos = db.execute("INSERT INTO log(kind, field_id, committed) VALUES ('create', ?, ?)",
                         (fid, created)).lastrowid
        db.execute("UPDATE fields SET position=? WHERE id=?", (pos, fid))
        snap_pos = pos if snap_seq else 0
        for seq, nrows, bcreated in db.execute(
                "SELECT seq, nrows, created FROM batches WHERE field_id=? ORDER BY seq",
                (fid,)).fetchall():
            bpos = db.execute("INSERT INTO log(kind, field_id, seq, nrows, committed) VALUES "
                              "('batch', ?, ?, ?, ?)", (fid, seq, nrows, bcreated)).lastrowid
            db.execute("UPDATE batches SET position=? WHERE field_id=? AND seq=?",
                       (bpos, fid, seq))
            if seq <= snap_seq:
                snap_pos = bpos
            nb += 1
        db.execute("UPDATE fields SET snapshot_position=? WHERE id=?", (snap_pos, fid))
    log.info("database migrated to schema %d: log backfilled with %d field(s), %d batch(es)",
             SCHEMA_VERSION, len(fields), nb)


class SQLiteBackend(LogBackend):
    """All durable state of a data directory (see the module doc). Thread-safe:
    writes go through one connection under a lock; reads use a connection per
    thread (WAL: readers never wait for the writer)."""

    kind = "sqlite"

    def __init__(self, data_dir: Path | str, *, lock_fd: int | None = None,
                 poll_interval: float = 0.005):
        self.data_dir = Path(data_dir)
        self.where = str(self.data_dir)
        self.snapshot_dir = self.data_dir / "snapshots"
        self.poll_interval = float(poll_interval)
        try:
            self.snapshot_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StorageError(f"cannot create the data directory {self.data_dir}: {exc}") from exc
        self._dir_lock = _lock_data_dir(self.data_dir, lock_fd)
        self.db_path = db_path = self.data_dir / DB_NAME
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._local = threading.local()
        self._closed = False
        try:
            self._db = self._connect()
            self._open_retrying()
        except (sqlite3.Error, StorageError) as exc:
            self.close()
            raise StorageError(f"cannot open the database {db_path}: {exc} (a damaged or "
                               "truncated file? restore it from a backup or move it away)"
                               ) from exc
        self._lock = threading.RLock()
        self._changed = threading.Event()
        self._watch: sqlite3.Connection | None = None
        self._watch_version: int | None = None

    @classmethod
    def from_settings(cls, settings) -> "SQLiteBackend":
        return cls(settings.data_dir, lock_fd=settings.lock_fd,
                   poll_interval=settings.log_poll_interval)

    def _open_retrying(self) -> None:
        """Page size, WAL and schema, retried while another replica of the group
        opens the same new database: SQLite answers the switch to WAL with
        'database is locked' at once, without waiting (its busy handler is not
        called there), when another connection holds the file meanwhile."""
        deadline = time.monotonic() + BUSY_TIMEOUT_S
        while True:
            try:
                # 64 KiB pages (new databases only): a batch blob of a few MB is
                # written as few WAL frames, and the auto-checkpoint (1000 pages)
                # runs every 64 MB instead of every 4 MB; durability is unchanged
                # (synchronous=FULL).
                self._db.execute("PRAGMA page_size=65536")
                self._db.execute("PRAGMA journal_mode=WAL")
                self._open_schema()
                return
            except sqlite3.OperationalError as exc:
                busy = "locked" in str(exc) or "busy" in str(exc)
                if not busy or time.monotonic() > deadline:
                    raise
                if self._db.in_transaction:
                    self._db.rollback()
                time.sleep(0.02)

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.db_path, check_same_thread=False, isolation_level=None,
                             timeout=BUSY_TIMEOUT_S)
        db.execute("PRAGMA synchronous=FULL")
        db.execute("PRAGMA foreign_keys=ON")
        with self._conns_lock:
            self._conns.append(db)
        return db

    def _open_schema(self) -> None:
        db = self._db
        ver = db.execute("PRAGMA user_version").fetchone()[0]
        if ver == SCHEMA_VERSION:
            return
        if ver not in (0, 2):
            raise StorageError(f"database schema version {ver}; this server knows "
                               f"{SCHEMA_VERSION}")
        # written only when needed (a full disk can still be read); several replicas
        # may open a new database at once: the version is checked again inside
        db.execute("BEGIN IMMEDIATE")
        try:
            ver = db.execute("PRAGMA user_version").fetchone()[0]
            if ver == 0:
                _run_script(db, _SCHEMA_V2)
                ver = 2
            if ver == 2:
                _migrate(db)
                db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise

    def check(self) -> None:
        """Refuse a damaged database: SQLite's ``quick_check`` (every page read once,
        about a second per GB; the blobs' contents are not checked).

        Raises
        ------
        StorageError
            Naming the file and what SQLite found.
        """
        rows = [r[0] for r in self._query("PRAGMA quick_check(5)")]
        if rows != ["ok"]:
            raise StorageError(f"the database {self.db_path} is damaged ({'; '.join(' '.join(r.split()) for r in rows)}); "
                               "restore it from a backup or move it away")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        ev = getattr(self, "_changed", None)
        if ev is not None:
            ev.set()
        lock = getattr(self, "_lock", None)
        if lock is not None:
            lock.acquire()
        try:
            with self._conns_lock:
                conns, self._conns = self._conns, []
            for c in conns:
                try:
                    c.close()
                except sqlite3.Error:  # pragma: no cover - a connection in use elsewhere
                    pass
        finally:
            if lock is not None:
                lock.release()
        self._dir_lock.close()  # releases the data directory (unless the group holds it)

    # -- transactions -----------------------------------------------------
    def _tx(self, fn: Callable[[sqlite3.Connection], object], *, appends: bool = True):
        """Run ``fn(db)`` in one write transaction (BEGIN IMMEDIATE: other processes'
        writers wait up to :data:`BUSY_TIMEOUT_S`); ``appends``: it appended to the
        log, so the follower is woken after the commit."""
        with self._lock:
            if self._closed:
                raise StorageError("storage is closed")
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    out = fn(self._db)
                    self._db.execute("COMMIT")  # may fail too (a full disk): roll back
                except BaseException:
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise storage_error(exc, self.db_path) from exc
        if appends:
            self._changed.set()
        return out

    def _reader(self) -> sqlite3.Connection:
        db = getattr(self._local, "db", None)
        if db is None:
            if self._closed:
                raise StorageError("storage is closed")
            db = self._local.db = self._connect()
        return db

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        try:
            return self._reader().execute(sql, args).fetchall()
        except sqlite3.Error as exc:
            raise storage_error(exc, self.db_path) from exc

    @staticmethod
    def _append(db, kind: str, field_id: int, seq: int = 0, nrows: int = 0) -> int:
        return db.execute("INSERT INTO log(kind, field_id, seq, nrows, committed) VALUES "
                          "(?, ?, ?, ?, ?)", (kind, field_id, seq, nrows, time.time())).lastrowid

    # -- fields -----------------------------------------------------------
    def create_field(self, name: str, spec: dict, basis: dict[str, np.ndarray]) -> tuple[int, int]:
        def fn(db):
            try:
                cur = db.execute(
                    "INSERT INTO fields(name, spec, basis, created) VALUES (?, ?, ?, ?)",
                    (name, json.dumps(spec), pack_arrays(basis), time.time()),
                )
            except sqlite3.IntegrityError:
                raise FieldExistsError(f"field {name!r} already exists") from None
            fid = cur.lastrowid
            pos = self._append(db, "create", fid)
            db.execute("UPDATE fields SET position=? WHERE id=?", (pos, fid))
            return fid, pos

        return self._tx(fn)

    def delete_field(self, field_id: int) -> int:
        snap: list[str] = []

        def fn(db):
            row = db.execute("SELECT snapshot_file FROM fields WHERE id=?", (field_id,)).fetchone()
            if row is None:
                raise FieldNotFoundError(f"field id {field_id} is not stored")
            if row[0]:
                snap.append(row[0])
            db.execute("DELETE FROM batches WHERE field_id=?", (field_id,))
            db.execute("DELETE FROM batch_results WHERE field_id=?", (field_id,))
            db.execute("DELETE FROM fields WHERE id=?", (field_id,))
            return self._append(db, "delete", field_id)

        pos = self._tx(fn)
        for f in snap:
            self._unlink(f)
        return pos

    _FIELD_COLS = ("SELECT id, name, spec, basis, created, position, snapshot_file, snapshot_seq,"
                   " snapshot_position FROM fields ")

    @staticmethod
    def _field_row(r) -> FieldRow:
        return FieldRow(r[0], r[1], json.loads(r[2]), unpack_arrays(r[3]), r[4], r[5], r[6],
                        r[7], r[8])

    def state(self) -> tuple[int, list[FieldRow]]:
        db = self._reader()
        try:
            db.execute("BEGIN")  # one read transaction: one snapshot of the database
            try:
                head = db.execute("SELECT COALESCE(MAX(position), 0) FROM log").fetchone()[0]
                rows = db.execute(self._FIELD_COLS + "ORDER BY id").fetchall()
            finally:
                db.execute("COMMIT")
        except sqlite3.Error as exc:
            raise storage_error(exc, self.db_path) from exc
        return int(head), [self._field_row(r) for r in rows]

    def fields(self) -> list[FieldRow]:
        return self.state()[1]

    def field(self, field_id: int) -> FieldRow:
        rows = self._query(self._FIELD_COLS + "WHERE id=?", (field_id,))
        if not rows:
            raise FieldNotFoundError(f"field id {field_id} is not stored")
        return self._field_row(rows[0])

    # -- batches ----------------------------------------------------------
    _BATCH_COLS = (
        "SELECT b.seq, b.position, b.idem_key, b.content_hash, b.form, b.nrows,"
        " COALESCE(r.result, b.result) FROM batches b"
        " LEFT JOIN batch_results r ON r.field_id=b.field_id AND r.seq=b.seq "
    )

    @staticmethod
    def _batch_row(r) -> BatchRow:
        return BatchRow(r[0], r[1], r[2], r[3], r[4], r[5], json.loads(r[6]))

    def find_batch(self, field_id: int, idem_key: str) -> BatchRow | None:
        rows = self._query(self._BATCH_COLS + "WHERE b.field_id=? AND b.idem_key=?",
                           (field_id, idem_key))
        return self._batch_row(rows[0]) if rows else None

    def add_batch(self, field_id: int, *, idem_key: str | None, chash: str, form: str,
                  nrows: int, blob: bytes,
                  result_fn: Callable[[int, int], dict] | None = None) -> tuple[int, int]:
        taken: list[BatchRow] = []

        def fn(db):
            snap = db.execute("SELECT snapshot_seq FROM fields WHERE id=?", (field_id,)).fetchone()
            if snap is None:
                raise FieldNotFoundError(f"field id {field_id} was deleted")
            if idem_key is not None:
                r = db.execute(self._BATCH_COLS + "WHERE b.field_id=? AND b.idem_key=?",
                               (field_id, idem_key)).fetchone()
                if r is not None:
                    taken.append(self._batch_row(r))
                    return None
            seq = db.execute(
                "SELECT COALESCE(MAX(seq), 0) + 1 FROM batches WHERE field_id=?", (field_id,)
            ).fetchone()[0]
            seq = max(seq, snap[0] + 1)
            pos = self._append(db, "batch", field_id, seq, nrows)
            db.execute(
                "INSERT INTO batches(field_id, seq, idem_key, content_hash, form, nrows, arrays,"
                " result, created, position) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (field_id, seq, idem_key, chash, form, nrows, blob, "null", time.time(), pos),
            )
            if result_fn is not None:  # in batch_results, where set_result writes too
                db.execute("INSERT INTO batch_results(field_id, seq, result) VALUES (?, ?, ?)",
                           (field_id, seq, json.dumps(result_fn(seq, pos))))
            return seq, pos

        out = self._tx(fn)
        if taken:
            raise KeyTakenError(taken[0])
        return out

    def set_result(self, field_id: int, seq: int, result: dict, *, replace: bool = True,
                   durable: bool = False) -> None:
        """Store the response of a batch committed without one. Not ``durable``: no
        fsync (see the module doc; a later commit or checkpoint makes it durable).
        ``replace=False`` keeps a response already stored."""
        verb = "INSERT OR REPLACE" if replace else "INSERT OR IGNORE"
        with self._lock:
            if self._closed:
                raise StorageError("storage is closed")
            try:
                if not durable:
                    self._db.execute("PRAGMA synchronous=NORMAL")
                try:
                    self._db.execute(
                        f"{verb} INTO batch_results(field_id, seq, result) SELECT ?, ?, ? "
                        "WHERE EXISTS (SELECT 1 FROM batches WHERE field_id=? AND seq=?)",
                        (field_id, seq, json.dumps(result), field_id, seq))
                finally:
                    self._db.execute("PRAGMA synchronous=FULL")
            except sqlite3.Error as exc:
                raise storage_error(exc, self.db_path) from exc

    def batches(self, field_id: int, after_seq: int = 0,
                upto_position: int | None = None) -> list[BatchRow]:
        sql = self._BATCH_COLS + "WHERE b.field_id=? AND b.seq>?"
        args: tuple = (field_id, after_seq)
        if upto_position is not None:
            sql += " AND b.position<=?"
            args += (upto_position,)
        return [self._batch_row(r) for r in self._query(sql + " ORDER BY b.seq", args)]

    def batch_arrays(self, field_id: int, seq: int) -> dict[str, np.ndarray]:
        """The stored arrays of one batch."""
        rows = self._query("SELECT arrays FROM batches WHERE field_id=? AND seq=?", (field_id, seq))
        if not rows:
            raise FieldNotFoundError(f"field id {field_id} has no batch {seq}")
        return unpack_arrays(rows[0][0])

    def batch_stats(self, field_id: int) -> tuple[int, int, int, int]:
        """(number of batches, rows, bytes of stored arrays, last seq)."""
        r = self._query(
            "SELECT COUNT(*), COALESCE(SUM(nrows), 0), COALESCE(SUM(LENGTH(arrays)), 0),"
            " COALESCE(MAX(seq), 0) FROM batches WHERE field_id=?",
            (field_id,),
        )[0]
        return int(r[0]), int(r[1]), int(r[2]), int(r[3])

    # -- the log ----------------------------------------------------------
    def head(self) -> int:
        return int(self._query("SELECT COALESCE(MAX(position), 0) FROM log")[0][0])

    def read_log(self, after: int, limit: int = 256) -> list[LogEntry]:
        rows = self._query("SELECT position, kind, field_id, seq, committed, nrows FROM log "
                           "WHERE position>? ORDER BY position LIMIT ?", (after, limit))
        return [LogEntry(*r) for r in rows]

    def wait_for_change(self, timeout: float) -> None:
        """Polls ``PRAGMA data_version`` (it changes when another connection, of this
        process or another, commits) every ``poll_interval`` seconds; this
        backend's own commits return it at once."""
        end = time.monotonic() + timeout
        try:
            if self._watch is None:
                self._watch = self._connect()
                self._watch_version = self._watch.execute("PRAGMA data_version").fetchone()[0]
            while not self._closed:
                if self._changed.is_set():
                    self._changed.clear()
                    return
                v = self._watch.execute("PRAGMA data_version").fetchone()[0]
                if v != self._watch_version:
                    self._watch_version = v
                    return
                left = end - time.monotonic()
                if left <= 0:
                    return
                self._changed.wait(min(self.poll_interval, left))
        except sqlite3.Error as exc:
            if self._closed:
                return
            raise storage_error(exc, self.db_path) from exc

    def wake(self) -> None:
        self._changed.set()

    # -- snapshots --------------------------------------------------------
    def snapshot_path(self, file: str) -> Path:
        return self.snapshot_dir / file

    def write_snapshot(self, field_id: int, seq: int, position: int,
                       save: Callable[[Path], None],
                       check: Callable[[], None] | None = None) -> SnapshotInfo:
        """Write a snapshot atomically, then point the field at it and announce it."""
        name = f"f{field_id}-s{seq}.snap"
        final = self.snapshot_dir / name
        tmp = self.snapshot_dir / f".tmp-{name}-{os.getpid()}-{threading.get_ident()}"
        try:
            save(tmp)
            if not tmp.exists():  # a writer that appended an extension
                cands = list(self.snapshot_dir.glob(tmp.name + ".*"))
                if len(cands) != 1:
                    raise StorageError(f"snapshot writer did not create {tmp}")
                tmp = cands[0]
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            size = tmp.stat().st_size
            if check is not None:
                check()
            os.replace(tmp, final)
            _fsync_dir(self.snapshot_dir)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StorageFullError(f"snapshot failed: {exc}") from exc
            raise StorageError(f"snapshot failed: {exc}") from exc
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        old: list[str] = []

        def fn(db):
            row = db.execute("SELECT snapshot_file FROM fields WHERE id=?", (field_id,)).fetchone()
            if row is None:
                raise FieldNotFoundError(f"field id {field_id} was deleted")
            if not final.is_file():  # removed since (a clean-up under a lease we lost)
                raise StorageError(f"snapshot {name} was removed before the field pointed at it")
            if row[0] and row[0] != name:
                old.append(row[0])
            db.execute("UPDATE fields SET snapshot_file=?, snapshot_seq=?, snapshot_position=? "
                       "WHERE id=?", (name, seq, position, field_id))
            return self._append(db, "snapshot", field_id, seq)

        try:
            pos = self._tx(fn)
        except BaseException:
            final.unlink(missing_ok=True)
            raise
        for o in old:
            self._unlink(o)
        return SnapshotInfo(name, size, pos)

    def load_snapshot(self, row: FieldRow, load: Callable[[Path], T]) -> T:
        path = self.snapshot_path(row.snapshot_file)
        try:
            return load(path)
        except OSError:
            if not path.exists():
                try:
                    now = self.field(row.id).snapshot_file
                except FieldNotFoundError:
                    now = None
                if now != row.snapshot_file:
                    raise SnapshotGoneError(f"snapshot {row.snapshot_file} was replaced") from None
            raise

    def snapshot_location(self, row: FieldRow) -> str:
        return str(self.snapshot_path(row.snapshot_file))

    def snapshot_bytes(self, row) -> int:
        file = row if isinstance(row, (str, type(None))) else row.snapshot_file
        if not file:
            return 0
        try:
            return self.snapshot_path(file).stat().st_size
        except OSError:
            return 0

    def acquire_lease(self, name: str, owner: str, ttl: float) -> bool:
        def fn(db):
            now = time.time()
            row = db.execute("SELECT owner, expires FROM leases WHERE name=?", (name,)).fetchone()
            if row is not None and row[0] != owner and row[1] > now and \
                    not _owner_dead(row[0]):
                return False
            db.execute("INSERT OR REPLACE INTO leases(name, owner, expires) VALUES (?, ?, ?)",
                       (name, owner, now + ttl))
            return True

        return self._tx(fn, appends=False)

    def renew_lease(self, name: str, owner: str, ttl: float) -> bool:
        def fn(db):
            now = time.time()
            return db.execute("UPDATE leases SET expires=? WHERE name=? AND owner=? AND "
                              "expires > ?", (now + ttl, name, owner, now)).rowcount == 1

        return self._tx(fn, appends=False)

    def release_lease(self, name: str, owner: str) -> None:
        self._tx(lambda db: db.execute("DELETE FROM leases WHERE name=? AND owner=?",
                                       (name, owner)), appends=False)

    def clean_orphans(self) -> int:
        """Remove snapshot files no field points at (left by a writer that died)."""
        keep = {f.snapshot_file for f in self.fields() if f.snapshot_file}
        n = 0
        for p in self.snapshot_dir.iterdir():
            if p.name not in keep and p.is_file():  # (never a directory mounted there)
                p.unlink(missing_ok=True)
                n += 1
        return n

    def _unlink(self, file: str) -> None:
        try:
            self.snapshot_path(file).unlink(missing_ok=True)
        except OSError as exc:  # pragma: no cover - best effort
            log.warning("could not remove snapshot %s: %s", file, exc)


#: the name the service used before it had several backends
Storage = SQLiteBackend
