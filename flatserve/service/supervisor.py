"""``flatserve serve --processes N``: N replica processes on one port.

The parent binds the listening socket and (SQLite backend) takes the data
directory's lock, then starts N children (``python -m flatserve.service`` with
the same settings) that inherit both: each runs uvicorn on the shared socket
(the kernel hands each new connection to one of them) and opens the data
directory with the inherited lock (``lock_fd``), so the N replicas share it
while any other server is refused. The parent holds no database connection and
serves no request: it restarts a child that dies (kill -9 included; the new one
restores and catches up from the log) and, on SIGTERM / SIGINT, stops them all
(each drains its follower). A child dies with the parent (``PR_SET_PDEATHSIG``),
so no replica outlives it holding the port.
"""
from __future__ import annotations

import ctypes
import functools
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

from prometheus_client import multiprocess
from pydantic import SecretStr

from .http.metrics import MULTIPROC_ENV
from .settings import Settings

log = logging.getLogger("flatserve.service")

#: a child that exits sooner than this after its start counts as a failed start
QUICK_EXIT_S = 5.0
#: failed starts in a row after which the supervisor gives up
MAX_QUICK_EXITS = 5
#: seconds children get to stop on SIGTERM before SIGKILL
STOP_TIMEOUT_S = 30.0
#: what a child runs (``python -c``): the supervisor's own installation (its first
#: argument) first on ``sys.path`` in place of the working directory, then the
#: server's entry point with the rest
CHILD_BOOT = ("import os, sys; root = sys.argv.pop(1); "
              "sys.path[:] = [root] + [p for p in sys.path if p not in ('', os.getcwd(), root)]; "
              "from flatserve.service.server import main; sys.exit(main(sys.argv[1:]))")


def child_command(*args: str) -> list[str]:
    """The command of a replica process: this interpreter, importing the same
    ``flatserve`` as this process whatever the working directory.

    ``python -m flatserve.service`` would put the working directory first on
    ``sys.path``: started in a source checkout, a child would import the source
    tree (without the built extension) instead of the installed package. The
    child puts the directory this process imported ``flatserve`` from first
    instead, and leaves the working directory off.
    """
    import flatserve

    root = os.path.dirname(os.path.dirname(os.path.abspath(flatserve.__file__)))
    return [sys.executable, "-c", CHILD_BOOT, root, *args]


def settings_env(settings: Settings) -> dict[str, str]:
    """``FLATSERVE_*`` variables that give a child process these settings."""
    env = {}
    for name in Settings.model_fields:
        v = getattr(settings, name)
        if v is None:
            continue
        if isinstance(v, SecretStr):
            v = v.get_secret_value()
        elif isinstance(v, bool):
            v = "true" if v else "false"
        elif isinstance(v, list):  # allowed_hosts, cors_origins: comma-separated
            v = ",".join(v)
        env[f"FLATSERVE_{name.upper()}"] = str(v)
    return env


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port``, inheritable by children."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def _die_with_parent(parent: int) -> None:  # pragma: no cover - in the child before exec
    """Ask for SIGTERM when the supervisor ``parent`` dies; if it died already (between
    the fork and this request, which then never fires), exit now."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    if os.getppid() != parent:  # re-parented: the supervisor is gone
        os._exit(1)


class Supervisor:
    """Starts, restarts and stops the replica processes (see the module doc).

    Parameters
    ----------
    settings : Settings
        ``processes`` children are started with these settings (``processes=1``).
    host : str
        The interface bound.
    """

    def __init__(self, settings: Settings, host: str):
        self.settings = settings
        self.host = host
        self.children: list[subprocess.Popen | None] = [None] * settings.processes
        self.started_at = [0.0] * settings.processes
        self.quick_exits = 0
        self.stopping = False

    def run(self) -> int:
        s = self.settings
        lock_fd = None
        if not s.database_url:
            from .log.storage import SQLiteBackend, lock_data_dir

            lock_fd = lock_data_dir(s.data_dir)  # DataDirInUseError: refused as one server
            SQLiteBackend(s.data_dir, lock_fd=lock_fd).close()  # create / migrate once
        sock = bind_socket(self.host, s.port)
        env = dict(os.environ, **settings_env(s))
        env.update(FLATSERVE_PROCESSES="1", FLATSERVE_HOST=self.host)
        # the replicas' metrics, summed by whichever answers a scrape (metrics.py)
        self.metrics_dir = tempfile.mkdtemp(prefix="flatserve-metrics-")
        env[MULTIPROC_ENV] = self.metrics_dir
        pass_fds = [sock.fileno()]
        if lock_fd is not None:
            env["FLATSERVE_LOCK_FD"] = str(lock_fd)
            pass_fds.append(lock_fd)
        self.cmd = child_command("--listen-fd", str(sock.fileno()))
        self.env, self.pass_fds = env, pass_fds
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        log.info("flatserve: %d replica processes on http://%s:%d (%s)", s.processes,
                 self.host, s.port, "PostgreSQL" if s.database_url else f"SQLite in {s.data_dir}")
        try:
            for i in range(s.processes):
                self._start(i)
            while not self.stopping:
                time.sleep(0.2)
                for i, p in enumerate(self.children):
                    if self.stopping or p is None or p.poll() is None:
                        continue
                    quick = time.monotonic() - self.started_at[i] < QUICK_EXIT_S
                    self.quick_exits = self.quick_exits + 1 if quick else 0
                    log.warning("replica %d (pid %d) exited with status %s; restarting it", i,
                                p.pid, p.returncode)
                    # its counters stay in the sum; its live gauges go
                    multiprocess.mark_process_dead(p.pid, self.metrics_dir)
                    if self.quick_exits >= MAX_QUICK_EXITS:
                        log.error("replicas keep failing at start; stopping")
                        self.stopping = True
                        break
                    if quick:
                        time.sleep(1.0)
                    self._start(i)
        finally:
            self._stop_all()
            shutil.rmtree(self.metrics_dir, ignore_errors=True)
            sock.close()
            if lock_fd is not None:
                os.close(lock_fd)
        return 1 if self.quick_exits >= MAX_QUICK_EXITS else 0

    def _start(self, i: int) -> None:
        env = dict(self.env, FLATSERVE_REPLICA=str(i))  # the `replica` label of its metrics
        self.children[i] = subprocess.Popen(self.cmd, env=env, pass_fds=self.pass_fds,
                                            preexec_fn=functools.partial(_die_with_parent, os.getpid()))
        self.started_at[i] = time.monotonic()
        log.info("replica %d started (pid %d)", i, self.children[i].pid)

    def _on_signal(self, signum, frame) -> None:
        self.stopping = True

    def _stop_all(self) -> None:
        live = [p for p in self.children if p is not None and p.poll() is None]
        for p in live:
            p.send_signal(signal.SIGTERM)
        end = time.monotonic() + STOP_TIMEOUT_S
        for p in live:
            try:
                p.wait(timeout=max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.children if p is not None]
