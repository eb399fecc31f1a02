"""Run the service with uvicorn (``flatserve serve`` / ``python -m flatserve.service``)."""
from __future__ import annotations

import argparse
import logging
import os
import sys

from ..parallel import set_shard_threads
from .settings import Settings

log = logging.getLogger("flatserve.service")


def limit_blas_threads(n: int = 1) -> str | None:
    """Cap NumPy's BLAS (OpenBLAS) at ``n`` threads in this process; returns what
    was capped, or None.

    The service's NumPy products are tall and thin ((n, m) @ (m, m-1) in the
    embedding): a threaded BLAS wakes its threads for them and leaves them
    spinning, which made a 50,000-row embedding take 16 ms instead of 0.3 ms and
    stole the cores from the native code (which has its own threads). Uses
    ``threadpoolctl`` when installed, else OpenBLAS's own setter (NumPy wheels).
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        pass
    else:
        threadpool_limits(n, user_api="blas")
        return "threadpoolctl"
    import ctypes
    import glob
    import os

    import numpy as np

    libs = os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libs, "*openblas*"))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in ("scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_",
                    "openblas_set_num_threads"):
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                return f"{os.path.basename(path)}:{sym}"
    return None


def serve(settings: Settings | None = None, listen_fd: int | None = None) -> None:
    """Run the service: one replica process, or with ``settings.processes`` > 1 a
    :class:`~.supervisor.Supervisor` of that many on one port. ``listen_fd``: an
    inherited listening socket to serve (a supervisor's child)."""
    import uvicorn

    from .app import app_ready, create_app

    settings = settings or Settings()
    from . import logs

    logs.configure(settings.log_level, settings.log_format)
    host = settings.bind_host()
    if host != settings.host and listen_fd is None:
        log.warning("no API key set: binding to %s instead of %s", host, settings.host)
    from .status import StorageError
    from .log.backend import open_backend

    if settings.processes > 1 and listen_fd is None:
        from .supervisor import Supervisor

        try:
            sys.exit(Supervisor(settings, host).run())
        except StorageError as exc:  # in use by another server, unreadable, damaged
            log.error("%s", exc)
            sys.exit(2)
    if settings.blas_threads:
        how = limit_blas_threads(settings.blas_threads)
        log.debug("BLAS threads capped at %d (%s)", settings.blas_threads, how)
    pool = set_shard_threads(settings.shard_threads)
    log.debug("a field's shards on %d threads", pool.threads)
    from .http.connections import connection_cap, guarded_protocol

    try:  # refuse at once, with a clear message, rather than in the middle of start-up
        storage = open_backend(settings)
        try:
            storage.check()
        finally:
            storage.close()
    except StorageError as exc:  # in use by another server, unreadable, damaged
        log.error("%s", exc)
        sys.exit(2)
    if settings.ray is not None:  # refuse at once when the cluster cannot be reached
        from .cluster.ray_env import connect
        from .status import ShardUnavailableError

        try:
            connect(settings)
        except ShardUnavailableError as exc:  # the address named
            log.error("%s", exc)
            sys.exit(2)
    where = f"log in {settings.database_url.split('@')[-1]}" if settings.database_url else \
        f"data in {settings.data_dir}"
    log.info("flatserve on http://%s:%d, %s, %d worker threads (pid %d)", host, settings.port,
             where, settings.workers, os.getpid())
    cap, note = connection_cap(settings.max_connections)
    if note:
        log.warning("%s", note)
    protocol = guarded_protocol(header_timeout=settings.header_timeout,
                                body_timeout=settings.body_timeout,
                                body_min_rate=settings.body_min_rate, max_connections=cap)
    # log_config=None: the logging configured above is uvicorn's too; its own access
    # log is off (flatserve's access log, logs.AccessLogMiddleware, has route and field)
    kw = dict(log_level=settings.log_level.lower(), access_log=False, log_config=None,
              timeout_graceful_shutdown=10, http=protocol,
              timeout_keep_alive=settings.keepalive_timeout)
    app = create_app(settings)
    sockets = None
    if listen_fd is None:
        config = uvicorn.Config(app, host=host, port=settings.port, workers=1, **kw)
    else:
        import socket

        sockets = [socket.socket(fileno=listen_fd)]  # family and type from the descriptor
        config = uvicorn.Config(app, **kw)
    if settings.accept_when_ready or listen_fd is not None:
        server = ready_first_server(config, lambda: app_ready(app))
    else:
        server = uvicorn.Server(config)
    server.run(sockets=sockets)


def ready_first_server(config, ready):
    """A uvicorn server that takes connections only once ``ready()`` is true: its
    lifespan (which starts the restore) runs first, then it waits (a SIGTERM
    meanwhile stops it), then it listens (its own port) or serves the inherited
    socket, whose connections until then go to the replicas that serve it."""
    import asyncio

    import uvicorn

    class ReadyFirstServer(uvicorn.Server):
        async def startup(self, sockets=None) -> None:
            lifespan_startup = self.lifespan.startup

            async def start_then_wait() -> None:
                await lifespan_startup()
                while not (self.should_exit or self.lifespan.should_exit or ready()):
                    await asyncio.sleep(0.05)
                if not self.should_exit and not self.lifespan.should_exit:
                    log.info("ready: taking connections")

            self.lifespan.startup = start_then_wait
            await super().startup(sockets=sockets)

    return ReadyFirstServer(config)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``flatserve serve``: one per setting (:class:`Settings`, whose field
    descriptions are the help), ``--data-dir`` for ``data_dir``; unset ones come from
    ``FLATSERVE_*`` variables or the defaults."""
    for name, f in Settings.model_fields.items():
        flag = "--" + name.replace("_", "-")
        env = f"FLATSERVE_{name.upper()}"
        default = f.default.get_secret_value() if hasattr(f.default, "get_secret_value") \
            else f.default
        doc = (f.description or name.replace("_", " ")).rstrip(".")
        if f.annotation is bool:
            if f.default is True:  # --access-log / --no-access-log
                p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None,
                               help=f"{doc} (default on; {env})")
            else:
                p.add_argument(flag, action="store_true", default=None, help=f"{doc} ({env})")
            continue
        kind = {int: int, float: float}.get(f.annotation, str)
        p.add_argument(flag, type=kind, help=f"{doc} (default {default}; {env})")


def settings_from_args(args: argparse.Namespace) -> Settings:
    over = {k: v for k, v in vars(args).items()
            if k in Settings.model_fields and v is not None}
    return Settings(**over)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m flatserve.service", description=__doc__)
    add_arguments(p)
    p.add_argument("--listen-fd", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    serve(settings_from_args(args), listen_fd=args.listen_fd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
