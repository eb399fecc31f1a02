"""A throwaway PostgreSQL cluster: ``initdb`` + ``pg_ctl`` on a temporary
directory and a free loopback port, for tests and benchmarks of the PostgreSQL
backend. Never the machine's own cluster: Debian's ``postgresql`` package
(``scripts/install-system-deps.sh --postgres``) only provides the binaries.

PostgreSQL refuses to run as root: under root every command runs as the
``postgres`` user (``runuser``), which owns the temporary directory.

Example
-------
>>> from tests.harness.pgcluster import PgCluster          # doctest: +SKIP
>>> with PgCluster() as pg:
...     url = pg.create_database("t1")      # postgresql://postgres@127.0.0.1:PORT/t1
...     pg.restart()                        # e.g. a fault-injection test
"""
from __future__ import annotations

import glob
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from .process import free_port

#: Where Debian puts each major version's binaries.
DEBIAN_BINDIRS = "/usr/lib/postgresql/*/bin"


class PgClusterError(RuntimeError):
    """The cluster could not be set up, started or stopped (the message holds
    the end of the server's log)."""


def find_bindir() -> Path:
    """The directory of ``initdb`` and ``pg_ctl``: ``FLATSERVE_PG_BINDIR``, else
    Debian's newest ``/usr/lib/postgresql/<major>/bin``, else the ``PATH``.

    Raises
    ------
    PgClusterError
        When none has ``initdb`` (with the command that installs it).
    """
    env = os.environ.get("FLATSERVE_PG_BINDIR")
    cands = [Path(env)] if env else []
    cands += sorted((Path(p) for p in glob.glob(DEBIAN_BINDIRS)),
                    key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0,
                    reverse=True)
    which = shutil.which("initdb")
    if which:
        cands.append(Path(which).parent)
    for c in cands:
        if (c / "initdb").is_file() and (c / "pg_ctl").is_file():
            return c
    raise PgClusterError("PostgreSQL's initdb was not found (install Debian's postgresql: "
                         "bash scripts/install-system-deps.sh --postgres; or set "
                         "FLATSERVE_PG_BINDIR)")


class PgCluster:
    """A PostgreSQL cluster of its own, in a temporary directory, on loopback.

    Parameters
    ----------
    fsync : bool
        PostgreSQL's ``fsync`` (on by default: benchmarks measure real commits;
        tests may turn it off, which loses nothing when only processes die,
        the machine does not).
    parent : str or path, optional
        Where the temporary directory goes (default: the system's temporary
        directory; it must be reachable by the ``postgres`` user under root).
    settings : dict, optional
        More ``postgresql.conf`` settings (``{"shared_buffers": "32MB"}``).
    start_timeout : float
        Seconds ``pg_ctl`` waits for the server to start or stop.

    Attributes
    ----------
    port : int
    dir : Path
        The temporary directory (``data/``, ``sock/``, ``server.log``).
    user : str
        The database superuser (``postgres``), trusted on loopback.

    The cluster is created and started on :meth:`start` (or entering ``with``),
    and stopped and removed by :meth:`close` (or leaving ``with``).
    """

    user = "postgres"

    def __init__(self, *, fsync: bool = True, parent=None, settings: dict | None = None,
                 start_timeout: float = 60.0):
        self.bindir = find_bindir()
        self.fsync = fsync
        self.settings = dict(settings or {})
        self.start_timeout = start_timeout
        self.as_postgres = os.geteuid() == 0
        if self.as_postgres:
            try:
                self._pw = pwd.getpwnam("postgres")
            except KeyError:
                raise PgClusterError("running as root needs the 'postgres' user (Debian's "
                                     "postgresql package creates it)") from None
        self.dir = Path(tempfile.mkdtemp(prefix="flatserve-pg-", dir=parent))
        self.data = self.dir / "data"
        self.sock = self.dir / "sock"
        self.logfile = self.dir / "server.log"
        self.port = 0
        self._initialised = False

    # -- commands ---------------------------------------------------------------
    def _run(self, *args: str, timeout: float = 120.0, check: bool = True
             ) -> subprocess.CompletedProcess:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        if self.as_postgres:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        p = subprocess.run(cmd, cwd=self.dir, capture_output=True, text=True, timeout=timeout,
                           env=dict(os.environ, LC_ALL="C", PGTZ="UTC"))
        if check and p.returncode != 0:
            raise PgClusterError(f"{' '.join(args[:2])} failed ({p.returncode}): "
                                 f"{p.stdout}{p.stderr}\n{self.log_tail()}")
        return p

    def log_tail(self, chars: int = 3000) -> str:
        """The end of the server's log."""
        try:
            return "server log:\n" + self.logfile.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def _init(self) -> None:
        if self.as_postgres:
            os.chown(self.dir, self._pw.pw_uid, self._pw.pw_gid)
        self.dir.chmod(0o700)
        self._run("initdb", "-D", str(self.data), "-U", self.user, "--auth=trust",
                  "--encoding=UTF8", "--locale=C", "--no-sync")
        if self.as_postgres:
            subprocess.run(["runuser", "-u", "postgres", "--", "mkdir", "-p", str(self.sock)],
                           check=True)
        else:
            self.sock.mkdir()
        self._initialised = True

    def _configure(self) -> None:
        conf = {
            "listen_addresses": "'127.0.0.1'",
            "port": str(self.port),
            "unix_socket_directories": f"'{self.sock}'",
            "fsync": "on" if self.fsync else "off",
            "shared_buffers": "'64MB'",
            "max_connections": "200",
            "log_min_messages": "warning",
            **{k: (v if isinstance(v, (int, float)) or str(v).startswith("'") else f"'{v}'")
               for k, v in self.settings.items()},
        }
        text = "\n# flatserve throwaway cluster\n" + "".join(f"{k} = {v}\n" for k, v in conf.items())
        # postgresql.auto.conf is read last: it wins over postgresql.conf
        auto = self.data / "postgresql.auto.conf"
        body = "".join(ln for ln in _read(auto).splitlines(True)
                       if not ln.startswith(("#", "\n")) and ln.split("=")[0].strip() not in conf)
        _write_as(auto, "# written by flatserve's PgCluster\n" + body + text, self.as_postgres)

    # -- life cycle -------------------------------------------------------------
    def start(self) -> "PgCluster":
        """initdb (first time), then ``pg_ctl start`` on a free port (another one if
        the port was taken meanwhile); returns once connections are accepted."""
        if not self._initialised:
            self._init()
        last = None
        for attempt in range(5):
            if not self.port or attempt:
                self.port = free_port()
            self._configure()
            p = self._run("pg_ctl", "-D", str(self.data), "-l", str(self.logfile), "-w",
                          "-t", str(int(self.start_timeout)), "start", check=False,
                          timeout=self.start_timeout + 30)
            if p.returncode == 0:
                return self
            last = f"{p.stdout}{p.stderr}\n{self.log_tail()}"
            if "already in use" not in last and "could not bind" not in last:
                break
        raise PgClusterError(f"PostgreSQL did not start: {last}")

    def postmaster_pid(self) -> int | None:
        """The server's process id while it runs (from ``postmaster.pid``)."""
        try:
            return int((self.data / "postmaster.pid").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return None

    def running(self) -> bool:
        p = self._run("pg_ctl", "-D", str(self.data), "status", check=False)
        return p.returncode == 0

    def stop(self, mode: str = "fast") -> None:
        """``pg_ctl stop -m mode``: ``fast`` (clients disconnected, a clean shutdown)
        or ``immediate`` (as a crash: recovery from the WAL on the next start)."""
        if self._initialised and self.running():
            self._run("pg_ctl", "-D", str(self.data), "-w", "-t", str(int(self.start_timeout)),
                      "-m", mode, "stop", timeout=self.start_timeout + 30)

    def restart(self, mode: str = "fast", down_s: float = 0.0) -> None:
        """Stop (``mode``), stay down ``down_s`` seconds, start on the same port."""
        self.stop(mode)
        time.sleep(down_s)
        p = self._run("pg_ctl", "-D", str(self.data), "-l", str(self.logfile), "-w",
                      "-t", str(int(self.start_timeout)), "start", check=False,
                      timeout=self.start_timeout + 30)
        if p.returncode != 0:
            raise PgClusterError(f"PostgreSQL did not restart: {p.stdout}{p.stderr}\n{self.log_tail()}")

    def close(self) -> None:
        """Stop the server (immediately: its data is thrown away) and remove the directory."""
        try:
            if self._initialised:
                pid = self.postmaster_pid()
                self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop",
                          check=False, timeout=90)
                end = time.monotonic() + 30  # pg_ctl returns once the pid file is gone
                while pid and process_alive(pid) and time.monotonic() < end:
                    time.sleep(0.02)
        finally:
            shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> "PgCluster":
        try:
            return self.start()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc) -> None:
        self.close()

    # -- databases --------------------------------------------------------------
    def url_of(self, database: str = "postgres") -> str:
        """``postgresql://postgres@127.0.0.1:PORT/database``."""
        return f"postgresql://{self.user}@127.0.0.1:{self.port}/{database}"

    @property
    def url(self) -> str:
        return self.url_of("postgres")

    def create_database(self, name: str) -> str:
        """``CREATE DATABASE name`` (a fresh one per test); returns its URL."""
        if not name.replace("_", "").isalnum():
            raise ValueError(f"database name {name!r}: letters, digits and _ only")
        self._run("psql", "-h", "127.0.0.1", "-p", str(self.port), "-U", self.user,
                  "-d", "postgres", "-v", "ON_ERROR_STOP=1", "-qc", f'CREATE DATABASE "{name}"')
        return self.url_of(name)


def process_alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its parent to reap it does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""


def _write_as(path: Path, text: str, as_postgres: bool) -> None:
    path.write_text(text)
    if as_postgres:
        st = path.parent.stat()
        os.chown(path, st.st_uid, st.st_gid)
    path.chmod(0o600)
