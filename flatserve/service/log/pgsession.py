"""The storage room's PostgreSQL sessions of their own: leases and change notification,
the parts of :class:`flatserve.service.log.pgstorage.PostgresBackend` that have no SQLite
counterpart in the rulebook (:mod:`.sqlrules`), as mixins it inherits.

* :class:`AdvisoryLeases`: a lease is a session-level advisory lock held on a
  connection of its own (it dies with its holder's connection); the ``leases``
  row says who holds it, for people looking. Each name is a lock of its own
  (a snapshot lease per field: :func:`~.backend.snapshot_lease`), so a process
  holding several holds a connection for each.
* :class:`LogListener`: :meth:`~LogListener.wait_for_change` LISTENs on a
  connection of its own for the ``NOTIFY`` each append sends, and wakes for
  this process's own commits through a pipe.

Both use the backend's ``_connect``, ``_run``, ``_error``, ``where`` and
``_closed``.
"""
from __future__ import annotations

import hashlib
import logging
import os
import select

import psycopg

log = logging.getLogger("flatserve.service.log.pgstorage")

#: NOTIFY channel of appends (payload: the position)
CHANNEL = "flatserve_log"


def _lease_key(name: str) -> int:
    """The advisory lock key of a lease (a signed 64-bit integer)."""
    h = hashlib.sha256(f"flatserve-lease:{name}".encode()).digest()
    return int.from_bytes(h[:8], "big", signed=True)


class AdvisoryLeases:
    """:meth:`LogBackend.acquire_lease`, ``renew_lease`` and ``release_lease`` as
    session advisory locks (state: ``_leases``, ``_lease_lock``)."""

    # -- leases ---------------------------------------------------------------------
    def acquire_lease(self, name: str, owner: str, ttl: float) -> bool:
        """The lease is a session-level advisory lock held on a connection of its own
        for as long as ``owner`` holds it: a holder killed with kill -9 loses it as
        soon as PostgreSQL sees its connection close (at once; a vanished host
        within the keepalive time), not after ``ttl``. The ``leases`` row says who
        holds it and until when it renews (``ttl``), for people looking."""
        with self._lease_lock:
            held = self._leases.get(name)
            if held is not None and held[0] != owner:
                return False  # another owner in this process
            if held is not None:
                try:  # a renewal on the session that holds the lock
                    self._lease_row(held[1], name, owner, ttl)
                    return True
                except psycopg.OperationalError:
                    # that session ended (PostgreSQL restarted, the backend was
                    # terminated) and the lock with it: take it again below
                    del self._leases[name]
                    held[1].close()
                except psycopg.Error as exc:
                    raise self._error(exc) from exc
            conn = None
            try:
                conn = self._connect()
                if not conn.execute("SELECT pg_try_advisory_lock(%s)",
                                    (_lease_key(name),)).fetchone()[0]:
                    conn.close()
                    return False
                self._lease_row(conn, name, owner, ttl)
            except psycopg.Error as exc:
                if conn is not None:
                    conn.close()
                raise self._error(exc) from exc
            self._leases[name] = (owner, conn)
            return True

    def renew_lease(self, name: str, owner: str, ttl: float) -> bool:
        """True only while the session that took the lock for ``owner`` lives: a
        session that ended released the lock (another replica may have held it
        since), so it is not taken again here."""
        with self._lease_lock:
            held = self._leases.get(name)
            if held is None or held[0] != owner:
                return False
            try:
                self._lease_row(held[1], name, owner, ttl)
                return True
            except psycopg.Error:
                del self._leases[name]
                held[1].close()
                return False

    @staticmethod
    def _lease_row(conn, name: str, owner: str, ttl: float) -> None:
        conn.execute(
            "INSERT INTO leases(name, owner, expires)"
            " VALUES (%s, %s, clock_timestamp() + make_interval(secs => %s))"
            " ON CONFLICT (name) DO UPDATE SET owner=EXCLUDED.owner, expires=EXCLUDED.expires",
            (name, owner, float(ttl)))

    def release_lease(self, name: str, owner: str) -> None:
        with self._lease_lock:
            held = self._leases.get(name)
            if held is not None and held[0] == owner:
                del self._leases[name]
                held[1].close()  # ends the session: its advisory lock goes with it
        self._run(lambda c: c.execute("DELETE FROM leases WHERE name=%s AND owner=%s",
                                      (name, owner)))


class LogListener:
    """:meth:`LogBackend.wait_for_change` and ``wake`` by LISTEN/NOTIFY (state:
    ``_listen``, ``_listen_lock``, ``_waiting``, the pipe ``_wake_r``/``_wake_w``)."""

    def wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # a byte is already waiting (or closed)

    def wait_for_change(self, timeout: float) -> None:
        """LISTEN on a connection of its own; after (re)connecting it returns at once
        (changes may have happened meanwhile)."""
        if self._closed:
            return
        if self._listen is None or self._listen.closed or self._listen.broken:
            if self._listen is not None:
                self._listen.close()
                self._listen = None
            try:
                conn = self._connect()
                conn.execute(f"LISTEN {CHANNEL}")
                self._listen = conn
            except psycopg.Error as exc:
                log.debug("LISTEN on %s failed: %s", self.where, exc)
                self._wait_pipe(min(timeout, 0.5))
            return
        conn = self._listen
        with self._listen_lock:
            if self._closed:
                return
            self._waiting = True
        try:
            fd = conn.fileno()
            r, _, _ = select.select([fd, self._wake_r], [], [], timeout)
        except (OSError, ValueError, psycopg.Error):
            r = []
        finally:
            with self._listen_lock:
                self._waiting = False
                if self._closed:
                    conn.close()
                    self._listen = None
        if self._closed:
            return
        if self._wake_r in r:
            self._drain_pipe()
        if fd in r:
            try:
                conn.pgconn.consume_input()
                while conn.pgconn.notifies() is not None:
                    pass
            except psycopg.Error:
                conn.close()  # reconnected on the next call
            if conn.pgconn.status != psycopg.pq.ConnStatus.OK:
                conn.close()

    def _wait_pipe(self, timeout: float) -> None:
        try:
            r, _, _ = select.select([self._wake_r], [], [], timeout)
        except (OSError, ValueError):
            return
        if r:
            self._drain_pipe()

    def _drain_pipe(self) -> None:
        try:
            while os.read(self._wake_r, 4096):
                pass
        except (BlockingIOError, OSError):
            pass
