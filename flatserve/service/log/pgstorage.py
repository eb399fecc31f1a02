"""The storage room's PostgreSQL backend (``FLATSERVE_DATABASE_URL=postgresql://...``):
replicas on several machines share one database. psycopg 3 (the ``postgres`` extra).

The domain rules (batch numbers, idempotency, pointing a field at a snapshot,
row mapping, error wording) are :mod:`.sqlrules`'s, the tables
:mod:`.sqlschema`'s; this module owns what is PostgreSQL's own: the connection
pool and its faults, the schema check (once, on the backend's first
connection), positions under an advisory lock, snapshots as chunk rows (:mod:`.pgsnapshots`), leases as session advisory locks and LISTEN/NOTIFY.

Everything lives in the schema ``flatserve`` of the database the URL names
(created on first use, by whichever replica comes first)::

    meta             schema version
    fields           id (never reused), name, spec JSON, basis blob, position of its
                     create entry, the snapshot it points at (name, seq, position)
    batches          (field_id, seq): position, idempotency key, content hash, form,
                     rows, the arrays (one blob, flatserve.service.log.blobs)
    batch_results    (field_id, seq): the response of each batch (JSON)
    log              position: kind (create | delete | batch | snapshot), field_id,
                     seq, commit time, rows
    snapshots        name: field_id, bytes      \\ a snapshot is chunked rows, so a
    snapshot_chunks  (name, idx): data (8 MiB)  / new replica needs only the URL
    leases           name: owner, renewal due (the lease itself is a session-level
                     advisory lock: it dies with its holder's connection)

**Positions in commit order.** Every transaction that appends to the log takes
the transaction-scoped advisory lock :data:`POSITION_LOCK` right before it draws
its position (a sequence) and holds it until it commits, so a reader that sees
position ``p`` sees every position below ``p`` that will ever commit (PostgreSQL
makes a transaction visible before it releases its locks). The slow part of an
upload (sending its arrays) happens before the lock: the lock covers a few
small statements and the commit. Per field, appends are serialised by the
field's row lock (``SELECT ... FOR UPDATE``) taken first: ``seq`` increases with
the position, and the lock order (field row, then the position lock) is the
same everywhere.

**Following.** Each append sends ``NOTIFY flatserve_log, '<position>'`` in its
transaction (delivered at commit). :meth:`PostgresBackend.wait_for_change`
listens on a connection of its own and also wakes for this process's own
commits (a pipe).

**Faults.** Connections come from a small pool; one found broken (a restart of
PostgreSQL, a network failure) is dropped with every idle one, and a statement
that had not begun is retried once on a new connection. Otherwise the error is
a :class:`~flatserve.service.status.StorageUnavailableError` (503 with ``Retry-After``):
a write whose commit was in flight may be stored or not; a retry with its
idempotency key tells, so nothing acknowledged is lost and nothing is stored
twice.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, TypeVar
from urllib.parse import urlsplit, urlunsplit

from . import sqlschema
from .pgsession import CHANNEL, AdvisoryLeases, LogListener
from .pgsnapshots import ChunkedSnapshots, Stages
from .sqlrules import Dialect, Failure, SQLBackend, storage_failure
from ..status import StorageError, StorageUnavailableError

try:
    import psycopg
    from psycopg import errors as pgerr
except ModuleNotFoundError as _exc:  # pragma: no cover - depends on the install
    raise StorageError("FLATSERVE_DATABASE_URL names PostgreSQL, which needs psycopg 3: "
                       "pip install 'flatserve[postgres]'") from _exc

log = logging.getLogger("flatserve.service.log.pgstorage")

T = TypeVar("T")

SCHEMA = "flatserve"
SCHEMA_VERSION = 1
#: advisory lock keys (one bigint each): the log's append order; schema creation
POSITION_LOCK = 0x666C6174_6C6F6701  # "flatlog" + 1
SCHEMA_LOCK = 0x666C6174_6C6F6702
#: bytes per snapshot chunk row

#: SQLSTATE classes of a server that is going away or cannot be reached
_UNAVAILABLE = ("08", "57P01", "57P02", "57P03", "53300")


def redact(url: str) -> str:
    """The URL without its password (for logs and error messages)."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return "postgresql://?"
    if parts.password is None:
        return url
    host = parts.hostname or ""
    if parts.port:
        host = f"{host}:{parts.port}"
    return urlunsplit(parts._replace(netloc=f"{parts.username}:***@{host}"))


#: PostgreSQL's spelling of the rulebook (:mod:`.sqlrules`): the arrays travel
#: before the position lock is taken; a result whose batch was deleted is a no-op
DIALECT = Dialect("postgresql", param="%s", blob_param="%b", for_update=" FOR UPDATE",
                  for_share=" FOR SHARE", arrays_before_position=True,
                  taken=(pgerr.UniqueViolation,), gone=(pgerr.ForeignKeyViolation,))


def storage_error(exc: Exception, where: str) -> StorageError:
    """The :class:`StorageError` for a psycopg error: out of space
    (:class:`StorageFullError`, 507), unreachable (:class:`StorageUnavailableError`,
    503 with ``Retry-After``), else :class:`StorageError` (503)."""
    state = getattr(exc, "sqlstate", None) or ""
    if isinstance(exc, pgerr.DiskFull) or state == "53100":
        kind = Failure.FULL
    elif (isinstance(exc, (psycopg.OperationalError, psycopg.InterfaceError))
            or state.startswith(_UNAVAILABLE)):
        kind = Failure.UNREACHABLE
    else:
        kind = Failure.FAILED
    return storage_failure(kind, exc, where)


class _Retry(Exception):
    """A pooled connection was found broken before anything was sent: retry once."""


class PostgresBackend(ChunkedSnapshots, AdvisoryLeases, LogListener, SQLBackend):
    """The replica log in PostgreSQL (see the module doc).

    Parameters
    ----------
    url : str
        ``postgresql://user:password@host:port/database`` (libpq's URL; its
        query parameters such as ``sslmode`` are passed on).
    tmp_dir : str or path, optional
        Where snapshots are staged on their way to and from the database
        (default: the system's temporary directory).
    connect_timeout : float
        Seconds to wait for one connection.
    start_timeout : float
        Seconds :meth:`check` (at start) keeps trying to reach the database
        (a replica and its database started together).
    pool_size : int
        Idle connections kept for reuse.
    """

    kind = "postgresql"
    dialect = DIALECT

    def __init__(self, url: str, *, tmp_dir=None, connect_timeout: float = 5.0,
                 start_timeout: float = 30.0, pool_size: int = 8):
        self.url = url
        self.where = redact(url)
        self.tmp_dir = Path(tmp_dir) if tmp_dir else None
        self.connect_timeout = connect_timeout
        self.start_timeout = start_timeout
        self.pool_size = pool_size
        self._idle: list[psycopg.Connection] = []
        self._pool_lock = threading.Lock()
        self._closed = False
        self._listen: psycopg.Connection | None = None
        self._listen_lock = threading.Lock()
        self._waiting = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._schema_ready = False
        self._schema_lock = threading.Lock()
        #: leases held: name -> (owner, the connection holding its advisory lock)
        self._leases: dict[str, tuple[str, psycopg.Connection]] = {}
        self._lease_lock = threading.Lock()
        self._stages = Stages(self.tmp_dir)
        self._stages.sweep()

    @classmethod
    def from_settings(cls, settings, *, follower: bool = False) -> "PostgresBackend":
        """From a server's :class:`~flatserve.service.settings.Settings`
        (``database_url``; snapshots are staged in ``data_dir`` when it exists).
        ``follower`` changes nothing: PostgreSQL takes every process alike."""
        data_dir = Path(settings.data_dir)
        return cls(settings.database_url, tmp_dir=data_dir if data_dir.is_dir() else None)

    # -- connections --------------------------------------------------------------
    def _connect(self) -> "psycopg.Connection":
        # TCP keepalives: a database that vanished without closing the connection
        # (a network partition, a host that died) is noticed within ~25 s
        conn = psycopg.connect(self.url, autocommit=True,
                               connect_timeout=max(1, int(self.connect_timeout)),
                               application_name="flatserve", keepalives=1, keepalives_idle=10,
                               keepalives_interval=5, keepalives_count=3)
        try:
            conn.execute(f"SET search_path TO {SCHEMA}")
            if not self._schema_ready:
                self._open_schema(conn)
        except BaseException:
            conn.close()
            raise
        return conn

    def _take(self) -> "psycopg.Connection":
        if self._closed:
            raise StorageError(f"storage is closed ({self.where})")
        with self._pool_lock:
            while self._idle:
                conn = self._idle.pop()
                if not conn.closed and not conn.broken:
                    return conn
                conn.close()
        try:
            return self._connect()
        except psycopg.Error as exc:
            raise storage_error(exc, self.where) from exc

    def _give(self, conn: "psycopg.Connection") -> None:
        if conn.closed or conn.broken or self._closed:
            conn.close()
            return
        with self._pool_lock:
            if len(self._idle) < self.pool_size:
                self._idle.append(conn)
                return
        conn.close()

    def _drop_all(self) -> None:
        with self._pool_lock:
            idle, self._idle = self._idle, []
        for c in idle:
            c.close()

    @contextmanager
    def _session(self, tx: bool, isolation: str | None = None
                 ) -> Iterator["psycopg.Connection"]:
        """A connection (in a transaction if ``tx``), returned to the pool after."""
        conn = self._take()
        began = False
        try:
            if tx:
                try:
                    conn.execute("BEGIN" + (f" ISOLATION LEVEL {isolation}" if isolation else ""))
                except psycopg.OperationalError as exc:
                    raise _Retry() from exc
                began = True
                yield conn
                conn.execute("COMMIT")
            else:
                yield conn
        except _Retry:
            conn.close()
            self._drop_all()
            raise
        except BaseException as exc:
            if began and not conn.closed and not conn.broken:
                try:
                    conn.execute("ROLLBACK")
                except psycopg.Error:
                    conn.close()
            if conn.broken or conn.closed:
                self._drop_all()
            self._give(conn)
            if isinstance(exc, psycopg.Error):
                raise storage_error(exc, self.where) from exc
            raise
        else:
            self._give(conn)

    def _run(self, fn: Callable[["psycopg.Connection"], T], *, tx: bool = True,
             isolation: str | None = None, write: bool = False) -> T:
        """``fn(conn)`` in a transaction (a stale pooled connection is replaced
        once). A write wakes this process's follower after its commit."""
        for attempt in range(2):
            try:
                with self._session(tx, isolation) as conn:
                    out = fn(conn)
                break
            except _Retry as r:
                if attempt:
                    raise storage_error(r.__cause__, self.where) from r.__cause__
            except StorageUnavailableError:
                # a read on a connection that broke: once more on a new one
                if write or attempt:
                    raise
                self._drop_all()
        if write:
            self.wake()
        return out

    def _error(self, exc: Exception) -> StorageError:
        return storage_error(exc, self.where)

    # -- the rulebook's hooks ---------------------------------------------------------
    def _write(self, fn: Callable[["psycopg.Connection"], T], *, appends: bool = True,
               durable: bool = True) -> T:
        """``fn(conn)`` in a transaction (not ``durable``: ``synchronous_commit``
        off for it); ``appends``: never retried (its commit may have landed), and
        this process's follower is woken after the commit."""
        def run(conn):
            if not durable:
                conn.execute("SET LOCAL synchronous_commit = off")
            return fn(conn)

        return self._run(run, write=appends)

    def _read(self, fn: Callable[["psycopg.Connection"], T], *, consistent: bool = False) -> T:
        if consistent:
            return self._run(fn, isolation="REPEATABLE READ")
        return self._run(fn, tx=False)

    def _rows(self, conn, sql: str, args: tuple = (), *, binary: bool = False) -> list:
        if not binary:
            return conn.execute(self.dialect.sql(sql), args).fetchall()
        with conn.cursor(binary=True) as cur:
            return cur.execute(self.dialect.sql(sql), args).fetchall()

    # -- life cycle -----------------------------------------------------------------
    def _open_schema(self, conn: "psycopg.Connection") -> None:
        """Create the schema if it is new, refuse another version: once per
        backend, on its first connection (:meth:`_connect`)."""
        with self._schema_lock:
            if self._schema_ready:
                return
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK,))
                have = conn.execute(
                    "SELECT 1 FROM information_schema.tables WHERE table_schema=%s"
                    " AND table_name='meta'", (SCHEMA,)).fetchone()
                if have:
                    row = conn.execute(
                        "SELECT value FROM meta WHERE key='schema_version'").fetchone()
                    ver = int(row[0]) if row else 0
                    if ver != SCHEMA_VERSION:
                        raise StorageError(f"the database {self.where} has flatserve schema "
                                           f"version {ver}; this server knows {SCHEMA_VERSION}")
                else:
                    conn.execute(f"CREATE SCHEMA IF NOT EXISTS {SCHEMA}")
                    conn.execute(f"SET search_path TO {SCHEMA}")
                    for stmt in sqlschema.ddl("postgresql"):
                        conn.execute(stmt)
                    conn.execute("INSERT INTO meta(key, value) VALUES ('schema_version', %s)",
                                 (str(SCHEMA_VERSION),))
            self._schema_ready = True

    def check(self) -> None:
        """Reach the database (trying for ``start_timeout`` seconds: a replica and
        its database may start together), create the schema if it is new, and
        refuse another schema version.

        Raises
        ------
        StorageError
            Unreachable after ``start_timeout`` seconds (naming the URL without
            its password), or a schema this server does not know.
        """
        end = time.monotonic() + self.start_timeout
        while True:
            try:
                self._give(self._take())  # a first connection checks the schema
                return
            except StorageUnavailableError as exc:
                if time.monotonic() >= end:
                    raise StorageError(f"cannot reach the database {self.where} "
                                       f"(tried for {self.start_timeout:g} s): {exc}") from exc
                log.warning("waiting for the database %s: %s", self.where, exc)
                time.sleep(0.5)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.wake()
        self._drop_all()
        with self._lease_lock:
            leases, self._leases = self._leases, {}
        for _, conn in leases.values():
            conn.close()
        with self._listen_lock:  # a wait in progress closes it on its way out
            if not self._waiting and self._listen is not None:
                self._listen.close()
                self._listen = None

    # -- the log ----------------------------------------------------------------------
    def _append(self, conn, kind: str, field_id: int, seq: int = 0, nrows: int = 0) -> int:
        """Draw the next position and append an entry (the position lock is held to
        the commit: see the module doc)."""
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (POSITION_LOCK,))
        pos = conn.execute("SELECT nextval('log_position')").fetchone()[0]
        conn.execute(
            "INSERT INTO log(position, kind, field_id, seq, committed, nrows)"
            " VALUES (%s, %s, %s, %s, extract(epoch FROM clock_timestamp()), %s)",
            (pos, kind, field_id, seq, nrows))
        conn.execute("SELECT pg_notify(%s, %s)", (CHANNEL, str(pos)))
        return pos

