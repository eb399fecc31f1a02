"""Run the service with uvicorn (``flatserve serve`` / ``python -m flatserve.service``)."""
from __future__ import annotations

import argparse
import logging
import sys

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


def serve(settings: Settings | None = None) -> None:
    import uvicorn

    from .app import create_app

    settings = settings or Settings()
    level = settings.log_level.upper()
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("flatserve").setLevel(level)
    if settings.blas_threads:
        how = limit_blas_threads(settings.blas_threads)
        log.debug("BLAS threads capped at %d (%s)", settings.blas_threads, how)
    host = settings.bind_host()
    if host != settings.host:
        log.warning("no API key set: binding to %s instead of %s", host, settings.host)
    from ..errors import StorageError
    from .connections import connection_cap, guarded_protocol
    from .storage import Storage

    try:  # refuse at once, with a clear message, rather than in the middle of start-up
        storage = Storage(settings.data_dir)
        try:
            storage.check()
        finally:
            storage.close()
    except StorageError as exc:  # in use by another server, unreadable, damaged
        log.error("%s", exc)
        sys.exit(2)
    log.info("flatserve on http://%s:%d, data in %s, %d worker threads", host, settings.port,
             settings.data_dir, settings.workers)
    cap, note = connection_cap(settings.max_connections)
    if note:
        log.warning("%s", note)
    protocol = guarded_protocol(header_timeout=settings.header_timeout,
                                body_timeout=settings.body_timeout,
                                body_min_rate=settings.body_min_rate, max_connections=cap)
    uvicorn.run(create_app(settings), host=host, port=settings.port, workers=1,
                log_level=settings.log_level.lower(), access_log=False,
                timeout_graceful_shutdown=10, http=protocol,
                timeout_keep_alive=settings.keepalive_timeout)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``flatserve serve``; unset ones come from FLATSERVE_* / defaults."""
    p.add_argument("--host", help="interface (default 127.0.0.1; FLATSERVE_HOST)")
    p.add_argument("--port", type=int, help="port (default 8000; FLATSERVE_PORT)")
    p.add_argument("--data-dir", help="data directory (default ./data; FLATSERVE_DATA_DIR)")
    p.add_argument("--workers", type=int, help="handler threads (FLATSERVE_WORKERS)")
    p.add_argument("--api-key", help="read-write API key (FLATSERVE_API_KEY)")
    p.add_argument("--read-only-key", help="read-only API key (FLATSERVE_READ_ONLY_KEY)")
    p.add_argument("--snapshot-every", type=int, help="samples between background snapshots")
    p.add_argument("--header-timeout", type=float,
                   help="seconds to receive a request's headers (default 10; "
                        "FLATSERVE_HEADER_TIMEOUT)")
    p.add_argument("--body-timeout", type=float,
                   help="seconds to receive a body, plus 1 s per --body-min-rate bytes "
                        "(default 60; FLATSERVE_BODY_TIMEOUT)")
    p.add_argument("--body-min-rate", type=int,
                   help="bytes/s that always get a body through (default 65536; "
                        "FLATSERVE_BODY_MIN_RATE)")
    p.add_argument("--keepalive-timeout", type=float,
                   help="seconds an idle keep-alive connection stays open (default 5; "
                        "FLATSERVE_KEEPALIVE_TIMEOUT)")
    p.add_argument("--max-connections", type=int,
                   help="open connections admitted, 503 beyond (default 1000; 0: as many as "
                        "ulimit -n allows; "
                        "FLATSERVE_MAX_CONNECTIONS)")
    p.add_argument("--log-level", help="debug, info, warning (FLATSERVE_LOG_LEVEL)")
    p.add_argument("--demo", action="store_true", default=None,
                   help="create the bunny light-field demo field on first start (FLATSERVE_DEMO)")


def settings_from_args(args: argparse.Namespace) -> Settings:
    over = {k: v for k, v in vars(args).items()
            if k in Settings.model_fields and v is not None}
    return Settings(**over)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m flatserve.service", description=__doc__)
    add_arguments(p)
    serve(settings_from_args(p.parse_args(argv)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
