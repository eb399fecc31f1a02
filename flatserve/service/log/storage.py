"""The storage room's SQLite backend (:class:`flatserve.service.log.backend.LogBackend`):
SQLite (WAL, ``synchronous=FULL``) plus snapshot files, in the data directory.

The domain rules (batch numbers, idempotency, pointing a field at a snapshot,
row mapping, error wording) are :mod:`.sqlrules`'s, the tables
:mod:`.sqlschema`'s; this module owns what is SQLite's own: the data
directory's lock, connections (one writer under a lock, a reader per thread),
the schema version and its migration, snapshot files, the lease row and
``PRAGMA data_version`` polling.

Layout of ``data_dir``::

    flatserve.sqlite3            fields, batches, batch_results, log, leases
    flatserve.lock               held (flock) by the server or replica group using it
    snapshots/f<id>-s<seq>.snap  the field file of field <id> after batch <seq> (save_parts)
    snapshots/parts/p<id>-<key>  the parts it names (an atlas field's charts; sqlitesnapshots.py)

Every change appends one row to ``log`` in its own transaction: SQLite has one
writer at a time, so the ``AUTOINCREMENT`` position drawn inside the write
transaction is in commit order. A batch is acknowledged only after its
transaction has committed (fsync'd by SQLite). Snapshots are written to a
temporary file, fsync'd, renamed into place and the directory fsync'd; only
then does the database point at them (and the log announce them).

Several processes may use one database: the replicas of one ``flatserve serve
--processes N``, which share the data directory's lock (an inherited open file,
``lock_fd``). Any other server finds the lock taken and refuses to start
(:class:`~flatserve.service.status.DataDirInUseError`). A *follower*
(``follower=True``: a shard worker of a one-machine cluster,
:mod:`..cluster.worker.shard`) takes no lock: it reads the log of the server that holds
the directory and stores snapshot parts (files), and never writes the database.

Schema versions: a new database is created at 3 (:func:`.sqlschema.ddl`); 2
(fields, batches, batch_results) is migrated on open to 3 (adds the log,
backfilled field by field in creation and batch order, the positions of
fields, batches and snapshots, and the leases).
"""
from __future__ import annotations

import logging
import sqlite3
import threading
import time
from pathlib import Path
from typing import Callable, TypeVar

from . import sqlschema
from .datadir import LOCK_NAME, fsync_path, hold_data_dir, lock_data_dir, owner_dead  # noqa: F401
from .sqlitemigrate import SCHEMA_V2 as _SCHEMA_V2, migrate_v2, run_script  # noqa: F401
from .sqlitesnapshots import SnapshotFiles
from .sqlrules import Dialect, Failure, SQLBackend, storage_failure
from ..status import StorageError

log = logging.getLogger("flatserve.service.log.storage")

T = TypeVar("T")

SCHEMA_VERSION = 3
DB_NAME = "flatserve.sqlite3"
#: seconds a writer waits for another process's write transaction
BUSY_TIMEOUT_S = 60.0

#: SQLite's spelling of the rulebook (:mod:`.sqlrules`)
DIALECT = Dialect("sqlite", param="?", blob_param="?", legacy_result=True,
                  taken=(sqlite3.IntegrityError,))


def storage_error(exc: sqlite3.Error, db_path: Path) -> StorageError:
    """The :class:`StorageError` for a database error (:class:`StorageFullError`
    when the disk is full); a damaged database is named."""
    code = getattr(exc, "sqlite_errorcode", None)
    if code == sqlite3.SQLITE_FULL or "disk is full" in str(exc):
        kind = Failure.FULL
    elif (code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
          or "malformed" in str(exc) or "not a database" in str(exc)):
        kind = Failure.DAMAGED
    else:
        kind = Failure.FAILED
    return storage_failure(kind, exc, str(db_path))


class SQLiteBackend(SnapshotFiles, SQLBackend):
    """All durable state of a data directory (see the module doc). Thread-safe:
    writes go through one connection under a lock; reads use a connection per
    thread (WAL: readers never wait for the writer)."""

    kind = "sqlite"
    dialect = DIALECT

    def __init__(self, data_dir: Path | str, *, lock_fd: int | None = None,
                 poll_interval: float = 0.005, follower: bool = False):
        self.data_dir = Path(data_dir)
        self.where = str(self.data_dir)
        self.snapshot_dir = self.data_dir / "snapshots"
        self.parts_dir = self.snapshot_dir / "parts"
        self.poll_interval = float(poll_interval)
        self.follower = bool(follower)
        self.db_path = db_path = self.data_dir / DB_NAME
        self._dir_lock = None
        if self.follower:
            if not db_path.is_file() or not self.parts_dir.is_dir():
                raise StorageError(
                    f"no flatserve database at {db_path}: a shard of a cluster on SQLite "
                    "reads the data directory of the server that holds it, so it must run "
                    "on that machine (a cluster of several machines needs PostgreSQL)")
        else:
            try:
                self.parts_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise StorageError(f"cannot create the data directory {self.data_dir}: "
                                   f"{exc}") from exc
            self._dir_lock = hold_data_dir(self.data_dir, lock_fd)
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._local = threading.local()
        self._closed = False
        try:
            self._db = self._connect()
            if self.follower:
                ver = self._db.execute("PRAGMA user_version").fetchone()[0]
                if ver != SCHEMA_VERSION:
                    raise StorageError(f"database schema version {ver}; this follower knows "
                                       f"{SCHEMA_VERSION} (the server holding it migrates it)")
            else:
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
    def from_settings(cls, settings, *, follower: bool = False) -> "SQLiteBackend":
        return cls(settings.data_dir, lock_fd=None if follower else settings.lock_fd,
                   poll_interval=settings.log_poll_interval, follower=follower)

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
            if ver == 0:  # a new database: the schema of today
                run_script(db, sqlschema.ddl("sqlite"))
            elif ver == 2:
                migrate_v2(db, SCHEMA_VERSION)
            if ver in (0, 2):
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
        if self._dir_lock is not None:
            self._dir_lock.close()  # releases the data directory (unless the group holds it)

    # -- transactions (the hooks of the rulebook) ------------------------------
    def _write(self, fn: Callable[[sqlite3.Connection], T], *, appends: bool = True,
               durable: bool = True) -> T:
        """``fn(db)`` in one write transaction (BEGIN IMMEDIATE: other processes'
        writers wait up to :data:`BUSY_TIMEOUT_S`); not ``durable``: without fsync
        (``synchronous=NORMAL``: a later commit or checkpoint makes it durable);
        ``appends``: the follower is woken after the commit."""
        with self._lock:
            if self._closed:
                raise StorageError("storage is closed")
            if self.follower:
                raise StorageError(f"{self.data_dir}: a follower never writes the database "
                                   "(the server holding the directory does)")
            db = self._db
            try:
                if not durable:
                    db.execute("PRAGMA synchronous=NORMAL")
                try:
                    db.execute("BEGIN IMMEDIATE")
                    try:
                        out = fn(db)
                        db.execute("COMMIT")  # may fail too (a full disk): roll back
                    except BaseException:
                        if db.in_transaction:
                            db.execute("ROLLBACK")
                        raise
                finally:
                    if not durable:
                        db.execute("PRAGMA synchronous=FULL")
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

    def _read(self, fn: Callable[[sqlite3.Connection], T], *, consistent: bool = False) -> T:
        """``fn(db)`` on this thread's reader (``consistent``: in one read
        transaction, one snapshot of the database; WAL: never waits)."""
        db = self._reader()
        try:
            if not consistent:
                return fn(db)
            db.execute("BEGIN")
            try:
                return fn(db)
            finally:
                db.execute("COMMIT")
        except sqlite3.Error as exc:
            raise storage_error(exc, self.db_path) from exc

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        return self._read(lambda db: db.execute(sql, args).fetchall())

    def _append(self, db, kind: str, field_id: int, seq: int = 0, nrows: int = 0) -> int:
        """The position: ``AUTOINCREMENT`` inside the (only) write transaction."""
        return db.execute("INSERT INTO log(kind, field_id, seq, nrows, committed) VALUES "
                          "(?, ?, ?, ?, ?)", (kind, field_id, seq, nrows, time.time())).lastrowid

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

    def acquire_lease(self, name: str, owner: str, ttl: float) -> bool:
        def fn(db):
            now = time.time()
            row = db.execute("SELECT owner, expires FROM leases WHERE name=?", (name,)).fetchone()
            if row is not None and row[0] != owner and row[1] > now and \
                    not owner_dead(row[0]):
                return False
            db.execute("INSERT OR REPLACE INTO leases(name, owner, expires) VALUES (?, ?, ?)",
                       (name, owner, now + ttl))
            return True

        return self._write(fn, appends=False)

    def renew_lease(self, name: str, owner: str, ttl: float) -> bool:
        def fn(db):
            now = time.time()
            return db.execute("UPDATE leases SET expires=? WHERE name=? AND owner=? AND "
                              "expires > ?", (now + ttl, name, owner, now)).rowcount == 1

        return self._write(fn, appends=False)

    def release_lease(self, name: str, owner: str) -> None:
        self._write(lambda db: db.execute("DELETE FROM leases WHERE name=? AND owner=?",
                                          (name, owner)), appends=False)


#: the name the service used before it had several backends
Storage = SQLiteBackend
