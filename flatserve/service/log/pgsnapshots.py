"""How snapshots travel on PostgreSQL (:mod:`.pgstorage`): as rows of
:data:`CHUNK_BYTES` in ``snapshot_chunks`` under a ``snapshots`` row, copied in
and out with ``COPY ... (FORMAT BINARY)`` through a local staging directory, so
that a new replica needs nothing but the database URL.

A staging directory is ``<tmp_dir>/flatserve-snap-<pid>-<random>``, held
locked (``flock`` on its ``.lock`` file) by its writer until it is done with it.
Replicas and other servers may share ``tmp_dir`` (a shared volume, the system's
temporary directory), whatever their process ids: :meth:`Stages.sweep` removes
only the directories whose lock nobody holds (left by a process killed with a
snapshot on its way), and never follows a symlink.
"""
from __future__ import annotations

import contextlib
import fcntl
import io
import logging
import os
import shutil
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Callable, TypeVar

from ...errors import SnapshotError
from .rows import FieldRow, SnapshotGoneError, SnapshotInfo
from .sqlrules import snapshot_failure, snapshot_name
from ..status import StorageError

log = logging.getLogger("flatserve.service.log.pgstorage")

T = TypeVar("T")

#: Bytes of one ``snapshot_chunks`` row.
CHUNK_BYTES = 8 << 20
#: Prefix of the snapshot staging directories (``<prefix><pid>-<random>``).
STAGE_PREFIX = "flatserve-snap-"
#: The file of a staging directory that its writer holds locked (``flock``).
STAGE_LOCK = ".lock"
#: Seconds after which a staging directory without a lock is an orphan.
STAGE_ORPHAN_AGE = 3600.0


class Stages:
    """The staging directories of one backend under ``tmp_dir`` (None: the
    system's temporary directory). Thread-safe."""

    def __init__(self, tmp_dir: Path | None):
        self.tmp_dir = tmp_dir
        self._fds: dict[Path, int] = {}  # staging directory -> its held lock
        self._guard = threading.Lock()

    def make(self) -> Path:
        """A private directory for one snapshot on its way, locked until
        :meth:`drop`: :meth:`sweep` of any process removes it only once nobody
        holds it."""
        d = Path(tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=self.tmp_dir))
        try:
            fd = os.open(d / ".lock-new", os.O_CREAT | os.O_RDWR, 0o600)
        except OSError:
            shutil.rmtree(d, ignore_errors=True)
            raise
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.rename(d / ".lock-new", d / STAGE_LOCK)  # visible to a sweep only once held
        with self._guard:
            self._fds[d] = fd
        return d

    def drop(self, d: Path) -> None:
        """Remove a directory of :meth:`make` and release its lock."""
        shutil.rmtree(d, ignore_errors=True)
        with self._guard:
            fd = self._fds.pop(d, None)
        if fd is not None:
            os.close(fd)

    def sweep(self) -> None:
        """Remove the staging directories left by processes that died with a
        snapshot on its way (kill -9 skips their cleanup): those whose lock
        nobody holds; a directory without a lock (being made, or from before
        there was one) once it is :data:`STAGE_ORPHAN_AGE` seconds old."""
        root = Path(self.tmp_dir) if self.tmp_dir else Path(tempfile.gettempdir())
        try:
            found = [p for p in root.iterdir() if p.name.startswith(STAGE_PREFIX)
                     and p.is_dir() and not p.is_symlink()]
        except OSError:
            return
        now = time.time()
        for p in found:
            try:
                fd = os.open(p / STAGE_LOCK, os.O_RDWR)
            except FileNotFoundError:
                try:
                    if now - p.stat().st_mtime < STAGE_ORPHAN_AGE:
                        continue
                except OSError:
                    continue
                fd = None
            except OSError:  # not ours to open
                continue
            try:
                if fd is not None:
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    except OSError:  # held: a live writer's
                        continue
                shutil.rmtree(p, ignore_errors=True)
            finally:
                if fd is not None:
                    os.close(fd)
            if not p.exists():
                log.info("removed the snapshot staging directory %s left by a process that "
                         "is gone", p)


def part_name(field_id: int, key: str) -> str:
    """The ``snapshots`` row name of field ``field_id``'s part ``key``."""
    return f"p{field_id}-{key}"


def _copy_in(conn, name: str, path: Path | io.BytesIO) -> None:
    """``path``'s bytes (a file, or bytes in memory) as the chunk rows of snapshot
    row ``name``."""
    with (path if isinstance(path, io.BytesIO) else open(path, "rb")) as fh, \
            conn.cursor() as cur, cur.copy(
            "COPY snapshot_chunks(name, idx, data) FROM STDIN (FORMAT BINARY)") as cp:
        cp.set_types(["text", "int4", "bytea"])
        idx = 0
        while True:
            chunk = fh.read(CHUNK_BYTES)
            if not chunk and idx:
                break
            cp.write_row((name, idx, chunk))
            idx += 1
            if len(chunk) < CHUNK_BYTES:
                break


def _copy_out(conn, name: str, path: Path | io.BytesIO) -> None:
    """Snapshot row ``name``'s chunks, in order, into the file ``path`` (or bytes
    in memory)."""
    with (contextlib.nullcontext(path) if isinstance(path, io.BytesIO) else open(path, "wb")) \
            as fh, conn.cursor(binary=True) as cur, cur.copy(
            "COPY (SELECT data FROM snapshot_chunks WHERE name=%s ORDER BY idx)"
            " TO STDOUT (FORMAT BINARY)", (name,)) as cp:
        cp.set_types(["bytea"])
        for (data,) in cp.rows():
            fh.write(data)


class ChunkedSnapshots:
    """:meth:`LogBackend.write_snapshot`, ``load_snapshot``, ``snapshot_parts``,
    ``snapshot_bytes`` and the hooks of ``clean_orphans`` of
    :class:`~.pgstorage.PostgresBackend`,
    with the rulebook's snapshot hooks (state: ``_stages``, a :class:`Stages`;
    statements through ``_run``). A snapshot's parts are ``snapshots`` rows of
    their own (``p<field id>-<key>``, each stored once), removed with their field
    or once no snapshot of the field names them."""

    def _stage(self) -> Path:
        """A locked private staging directory for one snapshot (:class:`Stages`)."""
        return self._stages.make()

    def _unstage(self, d: Path) -> None:
        self._stages.drop(d)

    def snapshot_parts(self, field_id: int) -> set[str]:
        prefix = part_name(field_id, "")
        rows = self._run(lambda c: c.execute(
            "SELECT name FROM snapshots WHERE field_id=%s AND name LIKE %s",
            (field_id, prefix + "%")).fetchall(), tx=False)
        return {r[0][len(prefix):] for r in rows}

    def store_part(self, field_id: int, key: str, data: bytes) -> int:
        """A ``snapshots`` row and its chunks, in a transaction of its own."""
        name = part_name(field_id, key)

        def store(conn) -> int:
            if not conn.execute("INSERT INTO snapshots(name, field_id, bytes, created)"
                                " VALUES (%s, %s, %s, %s) ON CONFLICT (name) DO NOTHING",
                                (name, field_id, len(data), time.time())).rowcount:
                return 0
            _copy_in(conn, name, io.BytesIO(data))
            return len(data)

        return self._run(store)

    def remove_parts(self, field_id: int, keys) -> None:
        names = [part_name(field_id, k) for k in keys]
        if names:
            self._run(lambda c: c.execute("DELETE FROM snapshots WHERE field_id=%s AND"
                                          " name = ANY(%s)", (field_id, names)))

    def write_snapshot(self, field_id: int, seq: int, position: int,
                       save: Callable[[Path, Path], list[str] | None],
                       check: Callable[[], None] | None = None) -> SnapshotInfo:
        stage = None
        name = f"f{field_id}-s{seq}-{uuid.uuid4().hex[:12]}.snap"
        try:
            stage = self._stage()
            parts_dir = stage / "parts"
            parts_dir.mkdir()
            path = stage / name
            keys = list(save(path, parts_dir) or [])
            if not path.exists():  # a writer that appended an extension
                cands = [p for p in stage.iterdir() if p.name not in (STAGE_LOCK, "parts")]
                if len(cands) != 1:
                    raise StorageError(f"snapshot writer did not create {path}")
                path = cands[0]
            size = path.stat().st_size
            new = sorted(parts_dir.iterdir())
            written = size + sum(p.stat().st_size for p in new)

            def store(conn):  # the data first, in a transaction of its own
                now = time.time()
                conn.execute("INSERT INTO snapshots(name, field_id, bytes, created)"
                             " VALUES (%s, %s, %s, %s)", (name, field_id, size, now))
                _copy_in(conn, name, path)
                for p in new:  # a part stored meanwhile (the same bytes) is kept as it is
                    pname = part_name(field_id, p.name)
                    if conn.execute("INSERT INTO snapshots(name, field_id, bytes, created)"
                                    " VALUES (%s, %s, %s, %s) ON CONFLICT (name) DO NOTHING",
                                    (pname, field_id, p.stat().st_size, now)).rowcount:
                        _copy_in(conn, pname, p)

            self._run(store)
        except OSError as exc:  # staging: out of space is a 507, as with SQLite
            raise snapshot_failure(exc) from exc
        finally:
            if stage is not None:
                self._unstage(stage)

        return SnapshotInfo(name, written, self._point(field_id, name, seq, position, check,
                                                        keys))

    def _forget_snapshot(self, conn, field_id: int, name: str | None) -> list[str]:
        # the snapshot and its parts, in the deleting transaction (chunks cascade)
        conn.execute("DELETE FROM snapshots WHERE field_id=%s", (field_id,))
        return []

    def _snapshot_stored(self, conn, name: str) -> bool:
        return conn.execute("SELECT 1 FROM snapshots WHERE name=%s FOR SHARE",
                            (name,)).fetchone() is not None

    def _parts_stored(self, conn, field_id: int, keys: list[str]) -> bool:
        names = sorted({part_name(field_id, k) for k in keys})
        got = conn.execute("SELECT name FROM snapshots WHERE name = ANY(%s) FOR SHARE",
                           (names,)).fetchall()
        return len(got) == len(names)

    def _discard_snapshots(self, names: list[str]) -> None:
        if not names:
            return
        try:
            self._run(lambda c: c.execute("DELETE FROM snapshots WHERE name = ANY(%s)", (names,)))
        except StorageError as exc:  # best effort: clean_orphans removes it later
            log.warning("could not remove snapshots %s: %s", names, exc)

    def _discard_parts(self, field_id: int, keep: list[str]) -> None:
        keep_names = [part_name(field_id, k) for k in keep]
        try:
            self._run(lambda c: c.execute(
                "DELETE FROM snapshots WHERE field_id=%s AND name LIKE %s"
                " AND NOT (name = ANY(%s))",
                (field_id, part_name(field_id, "") + "%", keep_names)))
        except StorageError as exc:  # best effort: the next snapshot removes them
            log.warning("could not remove the stale parts of field id %d: %s", field_id, exc)

    def read_part(self, field_id: int, key: str) -> bytes:
        name = part_name(field_id, key)

        def fetch(conn):  # one view of the row and its chunks
            if conn.execute("SELECT 1 FROM snapshots WHERE name=%s", (name,)).fetchone() is None:
                return None
            buf = io.BytesIO()
            _copy_out(conn, name, buf)
            return buf.getvalue()

        got = self._run(fetch, isolation="REPEATABLE READ")
        if got is None:
            raise SnapshotError(f"snapshot part {key} of field id {field_id} is missing")
        return got

    def load_snapshot(self, row: FieldRow, load: Callable[[Path, Callable[[str], bytes]], T]) -> T:
        """The snapshot's file staged; its parts read when ``load`` asks for them
        (:meth:`read_part`: a part of a field in tiles is read by the tile's own
        process, never staged here). A part gone meanwhile means the snapshot
        was replaced (a part goes only once no snapshot names it)."""
        if not row.snapshot_file:
            raise SnapshotGoneError(f"field id {row.id} has no snapshot")
        stage = self._stage()
        path = stage / row.snapshot_file
        try:
            def fetch(conn):
                if conn.execute("SELECT 1 FROM snapshots WHERE name=%s",
                                (row.snapshot_file,)).fetchone() is None:
                    return False
                _copy_out(conn, row.snapshot_file, path)
                return True

            try:
                found = self._run(fetch, isolation="REPEATABLE READ")
            except OSError as exc:
                raise StorageError(f"snapshot staging failed: {exc}") from exc
            if not found:
                raise SnapshotGoneError(f"snapshot {row.snapshot_file} of field id {row.id} "
                                        "was replaced")
            return self.load_with_parts(row, path, load)
        finally:
            self._unstage(stage)

    def snapshot_bytes(self, row) -> int:
        """Size of the row's snapshot (a :class:`FieldRow`, or its
        ``snapshot_file``) plus its field's parts."""
        file = snapshot_name(row)
        if not file:
            return 0
        r = self._run(lambda c: c.execute(
            "SELECT s.bytes + COALESCE((SELECT sum(p.bytes) FROM snapshots p"
            " WHERE p.field_id = s.field_id AND p.name LIKE 'p%%'), 0)"
            " FROM snapshots s WHERE s.name=%s", (file,)).fetchone(), tx=False)
        return 0 if r is None else int(r[0])

    #: snapshot rows (not parts) that no field points at
    _UNPOINTED = ("s.name NOT LIKE 'p%%' AND NOT EXISTS"
                  " (SELECT 1 FROM fields f WHERE f.snapshot_file = s.name)")

    def _orphan_fields(self) -> set[int]:
        rows = self._run(lambda c: c.execute(
            "SELECT DISTINCT s.field_id FROM snapshots s WHERE " + self._UNPOINTED +
            " AND EXISTS (SELECT 1 FROM fields f WHERE f.id = s.field_id)").fetchall(),
            tx=False)
        return {int(r[0]) for r in rows}

    def _clean_orphans(self, field_id: int | None) -> int:
        """``field_id``: its snapshots it does not point at (a writer that died
        between storing the data and pointing at it); None: every row of a
        field that is gone. One statement, one view: a row of a live field's
        writer is seen with its field (created before it)."""
        if field_id is not None:
            return self._run(lambda c: c.execute(
                "DELETE FROM snapshots s WHERE s.field_id = %s AND " + self._UNPOINTED,
                (field_id,)).rowcount)
        return self._run(lambda c: c.execute(
            "DELETE FROM snapshots s WHERE NOT EXISTS"
            " (SELECT 1 FROM fields f WHERE f.id = s.field_id)").rowcount)
