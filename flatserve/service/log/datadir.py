"""The storage room's data directory: the lock that keeps one server (or one
replica group, ``serve --processes N``) per directory, and the file-system
helpers the SQLite backend (:mod:`.storage`) needs beside it.

The lock is ``flock`` on ``<data_dir>/flatserve.lock`` (it holds the holder's
process id, for the message another server gets): released when the holder
closes it or dies, kill -9 included.
"""
from __future__ import annotations

import fcntl
import os
import socket
from pathlib import Path

from ..status import DataDirInUseError, StorageError

LOCK_NAME = "flatserve.lock"


def hold_data_dir(data_dir: Path, lock_fd: int | None = None):
    """Hold an exclusive lock on the data directory for this process's lifetime
    (released by :meth:`flatserve.service.log.storage.SQLiteBackend.close` or when the process dies, kill -9
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
    fh = hold_data_dir(data_dir)
    fd = os.dup(fh.fileno())
    fh.close()  # the dup keeps the open file description (and its lock)
    os.set_inheritable(fd, True)
    return fd


def owner_dead(owner: str) -> bool:
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
    return _exited(int(pid))


def _exited(pid: int) -> bool:
    """The process ``pid``, which ``kill(pid, 0)`` finds, has exited and waits to be
    reaped by its parent (a zombie, state Z or X in ``/proc/PID/stat``): a replica
    killed with ``kill -9`` stays one until its supervisor notices."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            stat = fh.read()
    except FileNotFoundError:
        return True  # gone meanwhile
    except OSError:  # no /proc here: trust kill(pid, 0)
        return False
    state = stat.rpartition(b")")[2].split()[:1]  # after "(comm)", which may hold spaces
    return state in ([b"Z"], [b"X"])


def fsync_path(path: Path) -> None:
    """fsync a file, or a directory (after a rename into it), by its path."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
