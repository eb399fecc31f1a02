"""The storage room's staging directories for PostgreSQL snapshots: local
temporary directories a snapshot passes through on its way to and from the
database (:mod:`.pgstorage` stores it as chunk rows).

A staging directory is ``<tmp_dir>/flatserve-snap-<pid>-<random>``, held
locked (``flock`` on its ``.lock`` file) by its writer until it is done with it.
Replicas and other servers may share ``tmp_dir`` (a shared volume, the system's
temporary directory), whatever their process ids: :meth:`Stages.sweep` removes
only the directories whose lock nobody holds (left by a process killed with a
snapshot on its way), and never follows a symlink.
"""
from __future__ import annotations

import fcntl
import logging
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

log = logging.getLogger("flatserve.service.pgstorage")

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
