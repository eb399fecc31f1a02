"""The server's demo field: a 360 degree light field of the bunny, built on first start.

:func:`ensure_demo_field` is called by the service at start-up (``make run``):
if the service has no field called ``bunny`` it creates an oriented covering
atlas field (``{"oriented": true, "basis": {"kind": "atlas", "atlas":
"covering"}}``: every ray direction lies well inside one of its charts),
samples the bunny with rays from eyes all around it
(:func:`flatserve.lightfield.sampling.orbit_samples`, as ``flatserve
lightfield orbit`` does) and uploads the samples in batches through the
service (so they are stored durably and restored on the next start), showing
a progress bar. Batches carry
idempotency keys, so a start interrupted half-way continues where it stopped.
The viewer can then orbit the whole way round.
"""
from __future__ import annotations

import logging
import sys
import time

import numpy as np

from ..atlas import object_unit
from .status import FieldExistsError, FieldNotFoundError
from ..flats import Flats
from ..lightfield.sampling import bunny_scene, orbit_samples
from .rooms import specs
from .http.docs import DEMO_VIEWER_FIELD
from .schemas import FieldCreate

__all__ = ["DEMO_FIELD", "DEMO_SAMPLES", "DEMO_BATCH", "DEMO_REQUEST", "ensure_demo_field",
           "start_demo_field", "viewer_url", "viewer_key_hint"]

log = logging.getLogger("flatserve.service")

#: Name of the demo field.
DEMO_FIELD = DEMO_VIEWER_FIELD
#: Rays sampled all around the bunny (README: build time on 2 cores).
DEMO_SAMPLES = 400_000
#: Rays per upload batch.
DEMO_BATCH = 50_000
#: The demo field's create request (less its name): a covering atlas of oriented
#: charts (rays keep their direction), as ``POST /v1/fields`` takes it; lengths in
#: the unit for the bunny's radius 0.5 (it fills the unit box): ``object_unit``, 1/3.
DEMO_REQUEST = {"k": 1, "d": 3, "channels": 1, "oriented": True, "unit": object_unit(0.5),
                "basis": {"kind": "atlas", "atlas": "covering"}}
#: How long to wait for the service to finish restoring stored fields.
READY_TIMEOUT_S = 3600.0


def viewer_url(host: str, port: int, name: str = DEMO_FIELD) -> str:
    """URL of the browser viewer of a field."""
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    if host in ("0.0.0.0", "[::]"):
        host = "127.0.0.1"
    return f"http://{host}:{port}/viewer/{name}"


def viewer_key_hint(settings, url: str) -> str:
    """What to add to a viewer URL when the server needs a key ('' when it does not):
    the read-only key in the URL's fragment or typed into the page, never the
    read-write key (a URL is kept in histories and shared)."""
    if not settings.auth_enabled:
        return ""
    if settings.read_only_key is None:
        return (" (this server needs a key and has no read-only one: set "
                "FLATSERVE_READ_ONLY_KEY and open the viewer with it; the page asks for it)")
    return (f" (this server needs a key: open {url}#key=READ_ONLY_KEY with the read-only "
            "key, FLATSERVE_READ_ONLY_KEY, or type it into the page)")


def ensure_demo_field(rooms, name: str = DEMO_FIELD, samples: int = DEMO_SAMPLES,
                      seed: int = 0, *, progress=True, batch: int = DEMO_BATCH):
    """Create the 360 degree bunny light field in a running service unless it is there.

    Parameters
    ----------
    rooms : flatserve.service.assembly.Rooms
        Must have started restoring (:meth:`~.assembly.Rooms.start`); this waits
        until it is ready.
    name : str
        Field name.
    samples : int
        Rays from eyes all around the bunny.
    seed : int
        Seed of the ray directions.
    progress : bool or callable(done, total)
        True: a progress bar on stderr when it is a terminal and the log is text
        (log lines go above it: :mod:`flatserve.service.logs`), else a log line at
        every tenth of the samples.
    batch : int
        Rays per upload batch.

    Returns
    -------
    FieldEntry
        The catalogue's entry of the field.
    """
    if not rooms.catalogue.ready.wait(READY_TIMEOUT_S):
        raise TimeoutError("stored fields did not finish loading")
    n = int(samples)
    nbatches = -(-n // batch)
    try:
        e = rooms.catalogue.get(name)
        if (e.spec.k, e.spec.d, e.spec.channels) != (1, 3, 1):
            log.warning("field %r exists but is not a grey light field; leaving it alone", name)
            return e
        if not e.spec.oriented:
            log.warning("field %r exists but is not a 360 degree (oriented atlas) field, as built "
                        "by earlier versions; leaving it alone (delete it to build the 360 "
                        "degree demo)", name)
            return e
        done = len(rooms.uploads.batches(e))
        if done >= nbatches:
            return e
        log.info("demo field %r: %d of %d batches stored; continuing", name, done, nbatches)
    except FieldNotFoundError:
        req = FieldCreate(name=name, **DEMO_REQUEST)
        spec, basis = specs.field_spec(req)
        try:
            e = rooms.fields.create(name, spec, basis)
        except FieldExistsError:  # another replica (serve --processes N) created it
            rooms.follower.wait_all_committed(rooms.settings.apply_wait_timeout)
            e = rooms.catalogue.get(name)
        log.info("demo field %r: building the 360 degree bunny light field from %d samples "
                 "(eyes all around it, %d charts)", name, n, len(spec.atlas["scales"]))
    t0 = time.perf_counter()
    bar = progress if callable(progress) else (
        _Progress(f"demo field {name!r}", n, rooms.settings.log_format) if progress else None)
    if bar is not None:
        bar(0, n)
    samples, values = orbit_samples(bunny_scene(1), n, seed)
    for i, lo in enumerate(range(0, n, batch)):
        hi = min(n, lo + batch)
        flats = Flats.from_rays(samples.origins[lo:hi], samples.directions[lo:hi])
        rooms.uploads.upload(e, flats, np.ascontiguousarray(values[lo:hi]),
                       idem_key=f"demo360-{name}-n{n}-s{seed}-b{batch}-{i}")
        if bar is not None:
            bar(hi, n)
    if isinstance(bar, _Progress):
        bar.close()
    log.info("demo field %r: %d samples in %.1f s", name, e.field.nsamples, time.perf_counter() - t0)
    return e


class _Progress:
    """``progress(done, total)`` of the demo's build: a tqdm bar on a terminal with text
    logs (the log handler writes above it), else an info line every tenth."""

    def __init__(self, label: str, total: int, log_format: str = "text"):
        self.label, self.total, self.next = label, max(int(total), 1), 0
        self.bar = None
        if log_format == "text" and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc=label, unit="rays", unit_scale=True)

    def __call__(self, done: int, total: int | None = None) -> None:
        if self.bar is not None:
            self.bar.update(done - self.bar.n)
        elif done >= self.next:
            log.info("%s: %d of %d samples uploaded", self.label, done, self.total)
            self.next = done + max(self.total // 10, 1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()



def start_demo_field(rooms, host: str, port: int, *, name: str = DEMO_FIELD,
                     samples: int = DEMO_SAMPLES, announce=None):
    """Run :func:`ensure_demo_field` in a daemon thread and announce the viewer URL.

    For the service's start-up (``make run``): the server answers at once
    while the field builds (the viewer page waits for it).

    Parameters
    ----------
    rooms : flatserve.service.assembly.Rooms
    host, port : the address the server listens on (for the URL)
    name, samples : see :func:`ensure_demo_field`
    announce : callable(str)
        Receives the "open the viewer at ..." line (default: logged, level info).

    Returns
    -------
    threading.Thread
    """
    import threading

    url = viewer_url(host, port, name)
    announce = announce or log.info
    how = viewer_key_hint(rooms.settings, url)

    def run():
        try:
            announce(f"flatserve: preparing the demo light field {name!r}; viewer: {url}{how}")
            ensure_demo_field(rooms, name, samples)
            announce(f"flatserve: demo field {name!r} ready - open {url}{how}")
        except Exception:  # the server keeps serving; the log says why
            log.exception("demo field %r could not be built", name)

    th = threading.Thread(target=run, name="flatserve-demo", daemon=True)
    th.start()
    return th
