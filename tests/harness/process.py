"""A flatserve server in a child process: for scripts, benchmarks and tests that
need a real server (its own interpreter, its own port, ``kill -9``).

Example
-------
>>> from tests.harness.process import ServerProcess        # doctest: +SKIP
>>> with ServerProcess("data", "server.log", snapshot_every=0) as srv:
...     srv.wait_ready()
...     print(srv.url)
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time


#: Starts of a server whose free port was taken before it bound it (:meth:`ServerProcess.wait_ready`).
PORT_TRIES = 3


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class ServerProcess:
    """``python -m flatserve.service`` on a free loopback port, in its own session.

    Parameters
    ----------
    data_dir : str or path
    log_path : str or path
        Its output is appended there.
    log_level : str
    command : list of str, optional
        The program and its first arguments (default ``python -m flatserve.service``;
        e.g. ``[".../bin/flatserve", "serve"]``, the installed script).
    cwd : path, optional
        Its working directory (default this process's).
    **options
        More settings as ``flatserve serve`` options (``snapshot_every=3000`` gives
        ``--snapshot-every 3000``). ``lock_fd`` (from
        :func:`flatserve.service.log.storage.lock_data_dir`) is inherited: the process
        joins that replica group on the data directory. ``processes=N``: N
        replica processes behind this one port (their supervisor is ``proc``).

    Leaving the ``with`` block kills the process and its children (``kill -9`` of
    its process group): none is ever left behind, whatever failed.
    """

    def __init__(self, data_dir, log_path, *, log_level: str = "info",
                 command: list[str] | None = None, cwd=None, **options):
        self._args = [*(command or [sys.executable, "-m", "flatserve.service"])]
        self._rest = ["--data-dir", str(data_dir), "--log-level", log_level]
        for k, v in options.items():
            self._rest += [f"--{k.replace('_', '-')}", str(v)]
        self._fds = (options["lock_fd"],) if options.get("lock_fd") is not None else ()
        self._cwd = cwd
        self.log_path = log_path
        self.log = open(log_path, "ab")
        self._spawn()

    def _spawn(self) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self._log_from = self.log.tell()
        self.proc = subprocess.Popen([*self._args, "--port", str(self.port), *self._rest], stdout=self.log,
                                     stderr=subprocess.STDOUT, start_new_session=True, pass_fds=self._fds,
                                     cwd=self._cwd)

    def _port_was_taken(self) -> bool:
        """The process exited because its port was taken between :func:`free_port`
        and its bind (another process took it: a Ray node's, a parallel test's)."""
        with open(self.log_path, "rb") as fh:
            fh.seek(self._log_from)
            return b"address already in use" in fh.read()

    def wait_ready(self, timeout: float = 90.0, interval: float = 0.05) -> None:
        """Wait until ``/readyz`` says ready; RuntimeError if the process exits,
        TimeoutError after ``timeout`` seconds. A process that exits because its
        free port was taken before it bound it is started again on another one (at
        most :data:`PORT_TRIES` times): ``port`` and ``url`` are then the new ones."""
        from flatserve.client import Client

        end = time.monotonic() + timeout
        for attempt in range(PORT_TRIES):
            with Client(self.url, retries=0, timeout=5) as c:
                while time.monotonic() < end:
                    if self.proc.poll() is not None:
                        break
                    if c.ready():
                        return
                    time.sleep(interval)
                else:
                    raise TimeoutError(f"server not ready after {timeout} s")
            if attempt + 1 == PORT_TRIES or not self._port_was_taken():
                raise RuntimeError(f"server exited with status {self.proc.returncode}")
            self._spawn()
        raise AssertionError("unreachable")

    def kill9(self) -> None:
        """``kill -9`` the process and its process group (replicas of ``processes``)
        and wait for it."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=60)
        self.log.close()

    def readyz(self) -> dict:
        """The replica's ``/readyz`` document (any status)."""
        import httpx

        return httpx.get(self.url + "/readyz", timeout=10).json()

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.kill9()


def children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (from ``/proc``)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    if int(fh.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, IndexError, ValueError):
                pass
    return out


def kill9_and_await_restart(parent: int, child: int, n: int, timeout: float = 30.0) -> list[int]:
    """kill -9 ``child`` of ``parent`` (a supervisor) and wait until ``parent`` has
    ``n`` children again, ``child`` not among them; those children."""
    os.kill(child, signal.SIGKILL)
    end = time.monotonic() + timeout
    now = children(parent)
    while time.monotonic() < end:
        now = children(parent)
        if len(now) == n and child not in now:
            return now
        time.sleep(0.05)
    raise AssertionError(f"pid {parent} did not restart its child {child}: children {now}")

