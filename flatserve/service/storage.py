"""Durable storage: SQLite (WAL, ``synchronous=FULL``) plus snapshot files.

Layout of ``data_dir``::

    flatserve.sqlite3            field definitions + every accepted sample batch
    snapshots/f<id>-s<seq>.snap  Field.save() (AtlasField.save()) of field <id> after batch <seq>

A batch row holds the raw input arrays (one blob, :mod:`.blobs`), its form
(``rays``, ``parametric`` or ``flats``), the idempotency key and a hash of the
content; its response (for idempotent retries) is in ``batch_results``, written
in the batch's own transaction and completed once a ``wait=true`` batch is
inserted. A batch is acknowledged only after its transaction has committed
(fsync'd by SQLite). Snapshots are written to a temporary file, fsync'd, renamed
into place and the directory fsync'd; only then does the database point at them.
One server holds the data directory at a time (an exclusive lock on
``flatserve.lock``).
"""
from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .blobs import pack_arrays, unpack_arrays
from ..errors import (DataDirInUseError, FieldExistsError, FieldNotFoundError, StorageError,
                      StorageFullError)

log = logging.getLogger("flatserve.service.storage")

SCHEMA_VERSION = 2
DB_NAME = "flatserve.sqlite3"

_SCHEMA = """
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


@dataclass
class FieldRow:
    id: int
    name: str
    spec: dict
    basis: dict[str, np.ndarray]
    created: float
    snapshot_file: str | None
    snapshot_seq: int


@dataclass
class BatchRow:
    seq: int
    idem_key: str | None
    content_hash: str
    form: str
    nrows: int
    #: the response sent for this batch; None if a crash lost it (see module doc)
    result: dict | None


LOCK_NAME = "flatserve.lock"


def _lock_data_dir(data_dir: Path):
    """Hold an exclusive lock on the data directory for this process's lifetime
    (released by :meth:`Storage.close` or when the process dies, kill -9 included).
    A second server on the same directory would diverge from the first: refused."""
    path = data_dir / LOCK_NAME
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


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Storage:
    """All durable state of a server. Thread-safe (one connection, one lock)."""

    def __init__(self, data_dir: Path | str):
        self.data_dir = Path(data_dir)
        self.snapshot_dir = self.data_dir / "snapshots"
        try:
            self.snapshot_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StorageError(f"cannot create the data directory {self.data_dir}: {exc}") from exc
        self._dir_lock = _lock_data_dir(self.data_dir)
        self.db_path = db_path = self.data_dir / DB_NAME
        try:
            self._db = sqlite3.connect(db_path, check_same_thread=False, isolation_level=None)
            # 64 KiB pages (new databases only): a batch blob of a few MB is written
            # as few WAL frames, and the auto-checkpoint (1000 pages) runs every 64 MB
            # instead of every 4 MB; durability is unchanged (synchronous=FULL).
            self._db.execute("PRAGMA page_size=65536")
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            ver = self._db.execute("PRAGMA user_version").fetchone()[0]
            if ver not in (0, SCHEMA_VERSION):
                raise StorageError(f"database schema version {ver}; this server knows {SCHEMA_VERSION}")
            if ver == 0:  # a new database (written only then: a full disk can still be read)
                self._db.executescript(_SCHEMA)
                self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        except (sqlite3.Error, StorageError) as exc:
            self._dir_lock.close()
            raise StorageError(f"cannot open the database {db_path}: {exc} (a damaged or "
                               "truncated file? restore it from a backup or move it away)"
                               ) from exc
        self._lock = threading.RLock()

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
        with self._lock:
            self._db.close()
        self._dir_lock.close()  # releases the data directory

    # -- transactions -----------------------------------------------------
    def _tx(self, fn: Callable[[sqlite3.Connection], object]):
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    out = fn(self._db)
                    self._db.execute("COMMIT")  # may fail too (a full disk): roll back
                    return out
                except BaseException:
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise storage_error(exc, self.db_path) from exc

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._db.execute(sql, args).fetchall()
            except sqlite3.Error as exc:
                raise storage_error(exc, self.db_path) from exc

    # -- fields -----------------------------------------------------------
    def create_field(self, name: str, spec: dict, basis: dict[str, np.ndarray]) -> int:
        def fn(db):
            try:
                cur = db.execute(
                    "INSERT INTO fields(name, spec, basis, created) VALUES (?, ?, ?, ?)",
                    (name, json.dumps(spec), pack_arrays(basis), time.time()),
                )
            except sqlite3.IntegrityError:
                raise FieldExistsError(f"field {name!r} already exists") from None
            return cur.lastrowid

        return self._tx(fn)

    def delete_field(self, field_id: int) -> None:
        rows = self._query("SELECT snapshot_file FROM fields WHERE id=?", (field_id,))

        def fn(db):
            db.execute("DELETE FROM batches WHERE field_id=?", (field_id,))
            db.execute("DELETE FROM batch_results WHERE field_id=?", (field_id,))
            db.execute("DELETE FROM fields WHERE id=?", (field_id,))

        self._tx(fn)
        if rows and rows[0][0]:
            self._unlink(rows[0][0])

    def fields(self) -> list[FieldRow]:
        rows = self._query(
            "SELECT id, name, spec, basis, created, snapshot_file, snapshot_seq FROM fields ORDER BY id"
        )
        return [
            FieldRow(r[0], r[1], json.loads(r[2]), unpack_arrays(r[3]), r[4], r[5], r[6])
            for r in rows
        ]

    def field(self, field_id: int) -> FieldRow:
        for f in self.fields():
            if f.id == field_id:
                return f
        raise FieldNotFoundError(f"field id {field_id} not stored")

    # -- batches ----------------------------------------------------------
    _BATCH_COLS = (
        "SELECT b.seq, b.idem_key, b.content_hash, b.form, b.nrows,"
        " COALESCE(r.result, b.result) FROM batches b"
        " LEFT JOIN batch_results r ON r.field_id=b.field_id AND r.seq=b.seq "
    )

    def find_batch(self, field_id: int, idem_key: str) -> BatchRow | None:
        rows = self._query(self._BATCH_COLS + "WHERE b.field_id=? AND b.idem_key=?",
                           (field_id, idem_key))
        if not rows:
            return None
        r = rows[0]
        return BatchRow(r[0], r[1], r[2], r[3], r[4], json.loads(r[5]))

    def add_batch(self, field_id: int, *, idem_key: str | None, chash: str, form: str,
                  nrows: int, blob: bytes,
                  result_fn: Callable[[int], dict] | None = None) -> int:
        """Store one batch; commit (durable) before returning its ``seq``.

        ``result_fn(seq)`` builds a response stored with the batch (so a retry
        with the same idempotency key gets the same answer); without it, or to
        replace it, :meth:`set_result` stores one later.
        """
        def fn(db):
            seq = db.execute(
                "SELECT COALESCE(MAX(seq), 0) + 1 FROM batches WHERE field_id=?", (field_id,)
            ).fetchone()[0]
            snap = db.execute("SELECT snapshot_seq FROM fields WHERE id=?", (field_id,)).fetchone()
            if snap is None:
                raise FieldNotFoundError(f"field id {field_id} was deleted")
            seq = max(seq, snap[0] + 1)
            db.execute(
                "INSERT INTO batches(field_id, seq, idem_key, content_hash, form, nrows, arrays,"
                " result, created) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (field_id, seq, idem_key, chash, form, nrows, blob, "null", time.time()),
            )
            if result_fn is not None:  # in batch_results, where set_result writes too
                db.execute("INSERT INTO batch_results(field_id, seq, result) VALUES (?, ?, ?)",
                           (field_id, seq, json.dumps(result_fn(seq))))
            return seq

        return self._tx(fn)

    def set_result(self, field_id: int, seq: int, result: dict, replace: bool = True,
                   durable: bool = False) -> None:
        """Store the response of a batch committed without one. Not ``durable``: no
        fsync (see the module doc; a later commit or checkpoint makes it durable).
        ``replace=False`` keeps a response already stored."""
        verb = "INSERT OR REPLACE" if replace else "INSERT OR IGNORE"
        with self._lock:
            try:
                if not durable:
                    self._db.execute("PRAGMA synchronous=NORMAL")
                try:
                    self._db.execute(
                        f"{verb} INTO batch_results(field_id, seq, result) VALUES (?, ?, ?)",
                        (field_id, seq, json.dumps(result)))
                finally:
                    self._db.execute("PRAGMA synchronous=FULL")
            except sqlite3.Error as exc:
                raise storage_error(exc, self.db_path) from exc

    def batches(self, field_id: int) -> list[BatchRow]:
        rows = self._query(self._BATCH_COLS + "WHERE b.field_id=? ORDER BY b.seq", (field_id,))
        return [BatchRow(r[0], r[1], r[2], r[3], r[4], json.loads(r[5])) for r in rows]

    def batch_arrays(self, field_id: int, seq: int) -> dict[str, np.ndarray]:
        """The stored arrays of one batch."""
        rows = self._query("SELECT arrays FROM batches WHERE field_id=? AND seq=?", (field_id, seq))
        if not rows:
            raise FieldNotFoundError(f"field id {field_id} has no batch {seq}")
        return unpack_arrays(rows[0][0])

    def iter_batch_arrays(self, field_id: int, after_seq: int = 0
                          ) -> Iterator[tuple[int, str, dict[str, np.ndarray]]]:
        """Yield ``(seq, form, arrays)`` of the batches after ``after_seq``, in order."""
        seqs = self._query(
            "SELECT seq FROM batches WHERE field_id=? AND seq>? ORDER BY seq", (field_id, after_seq)
        )
        for (seq,) in seqs:
            rows = self._query(
                "SELECT form, arrays FROM batches WHERE field_id=? AND seq=?", (field_id, seq)
            )
            if rows:
                yield seq, rows[0][0], unpack_arrays(rows[0][1])

    def batch_stats(self, field_id: int) -> tuple[int, int, int, int]:
        """(number of batches, rows, bytes of stored arrays, last seq)."""
        r = self._query(
            "SELECT COUNT(*), COALESCE(SUM(nrows), 0), COALESCE(SUM(LENGTH(arrays)), 0),"
            " COALESCE(MAX(seq), 0) FROM batches WHERE field_id=?",
            (field_id,),
        )[0]
        return int(r[0]), int(r[1]), int(r[2]), int(r[3])

    # -- snapshots --------------------------------------------------------
    def snapshot_path(self, file: str) -> Path:
        return self.snapshot_dir / file

    def write_snapshot(self, field_id: int, seq: int, save: Callable[[Path], None]) -> Path:
        """Write a snapshot atomically and make the database point at it."""
        name = f"f{field_id}-s{seq}.snap"
        final = self.snapshot_dir / name
        tmp = self.snapshot_dir / f".tmp-{name}-{threading.get_ident()}"
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
            if row[0] and row[0] != name:
                old.append(row[0])
            db.execute(
                "UPDATE fields SET snapshot_file=?, snapshot_seq=? WHERE id=?", (name, seq, field_id)
            )

        try:
            self._tx(fn)
        except BaseException:
            final.unlink(missing_ok=True)
            raise
        for o in old:
            self._unlink(o)
        return final

    def snapshot_bytes(self, file: str | None) -> int:
        if not file:
            return 0
        try:
            return self.snapshot_path(file).stat().st_size
        except OSError:
            return 0

    def clean_orphans(self) -> int:
        """Remove snapshot files no field points at (left by a crash)."""
        keep = {f.snapshot_file for f in self.fields() if f.snapshot_file}
        n = 0
        for p in self.snapshot_dir.iterdir():
            if p.name not in keep:
                p.unlink(missing_ok=True)
                n += 1
        return n

    def _unlink(self, file: str) -> None:
        try:
            self.snapshot_path(file).unlink(missing_ok=True)
        except OSError as exc:  # pragma: no cover - best effort
            log.warning("could not remove snapshot %s: %s", file, exc)
