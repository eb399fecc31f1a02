"""The server's demo field: the paper's bunny light field, built on first start.

:func:`ensure_demo_field` is called by the service at start-up (``make run``):
if the registry has no field called ``bunny`` it creates one with the paper's
basis, samples the bunny (Sec. 5.2) and uploads the samples in batches
through the registry (so they are stored durably and restored on the next
start), showing a progress bar. Batches carry idempotency keys, so a start
interrupted half-way continues where it stopped.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from ..errors import FieldExistsError, FieldNotFoundError
from ..flats import Flats
from ..lightfield.sampling import BASIS_SCALE, ProgressBar, bunny_scene, sample_scene
from . import specs, uploads
from .entry import FieldSpec
from .schemas import TangentSimplexBasis

__all__ = ["DEMO_FIELD", "DEMO_N", "DEMO_BATCH", "ensure_demo_field", "start_demo_field", "viewer_url"]

log = logging.getLogger("flatserve.service")

#: Name of the demo field.
DEMO_FIELD = "bunny"
#: Screen side of the demo samples (DEMO_N^2 rays; the paper uses 1000).
DEMO_N = 600
#: Rays per upload batch.
DEMO_BATCH = 50_000
#: How long to wait for the registry to finish restoring stored fields.
READY_TIMEOUT_S = 3600.0


def viewer_url(host: str, port: int, name: str = DEMO_FIELD) -> str:
    """URL of the browser viewer of a field."""
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    if host in ("0.0.0.0", "[::]"):
        host = "127.0.0.1"
    return f"http://{host}:{port}/viewer/{name}"


def ensure_demo_field(registry, name: str = DEMO_FIELD, n: int = DEMO_N, seed: int = 0, *,
                      progress=True, batch: int = DEMO_BATCH):
    """Create the bunny light field in a running registry unless it is there.

    Parameters
    ----------
    registry : flatserve.service.registry.Registry
        Must have started restoring (``load_stored`` in its thread); this
        waits until it is ready.
    name : str
        Field name.
    n : int
        Samples on an n x n screen.
    seed : int
        Seed of the eye positions.
    progress : bool or callable(done, total)
        True: a text progress bar on stderr.
    batch : int
        Rays per upload batch.

    Returns
    -------
    FieldEntry
        The registry's entry of the field.
    """
    if not registry.ready.wait(READY_TIMEOUT_S):
        raise TimeoutError("stored fields did not finish loading")
    nbatches = -(-n * n // batch)
    try:
        e = registry.get(name)
        if (e.spec.k, e.spec.d, e.spec.channels) != (1, 3, 1):
            log.warning("field %r exists but is not a grey light field; leaving it alone", name)
            return e
        done = registry.storage.batch_stats(e.id)[0]
        if done >= nbatches:
            return e
        log.info("demo field %r: %d of %d batches stored; continuing", name, done, nbatches)
    except FieldNotFoundError:
        # the paper's basis: tangent simplex around the z-axis, scale 0.01
        spec = TangentSimplexBasis(scale=BASIS_SCALE)
        basis = specs.build_basis(spec, 1, 3)
        try:
            e = registry.create(name, FieldSpec(1, 3, 1, specs.spec_dict(spec)), basis)
        except FieldExistsError:  # another replica (serve --processes N) created it
            registry.wait_all_committed()
            e = registry.get(name)
        log.info("demo field %r: building the bunny light field from %d^2 samples", name, n)
    t0 = time.perf_counter()
    scene = bunny_scene(1)
    samples, values = sample_scene(scene, n, seed)
    bar = progress if callable(progress) else (ProgressBar(f"building demo field {name!r}", n * n) if progress else None)
    for i, lo in enumerate(range(0, n * n, batch)):
        hi = min(n * n, lo + batch)
        flats = Flats.from_rays(samples.origins[lo:hi], samples.directions[lo:hi])
        uploads.upload(registry, e, flats, np.ascontiguousarray(values[lo:hi]),
                       idem_key=f"demo-{name}-n{n}-s{seed}-b{batch}-{i}")
        if bar is not None:
            bar(hi, n * n)
    log.info("demo field %r: %d samples in %.1f s", name, e.field.nsamples, time.perf_counter() - t0)
    return e



def start_demo_field(registry, host: str, port: int, *, name: str = DEMO_FIELD, n: int = DEMO_N,
                     announce=print):
    """Run :func:`ensure_demo_field` in a daemon thread and announce the viewer URL.

    For the service's start-up (``make run``): the server answers at once
    while the field builds (the viewer page waits for it).

    Parameters
    ----------
    registry : Registry
    host, port : the address the server listens on (for the URL)
    name, n : see :func:`ensure_demo_field`
    announce : callable(str)
        Receives the "open the viewer at ..." line (default print).

    Returns
    -------
    threading.Thread
    """
    import threading

    url = viewer_url(host, port, name)

    def run():
        try:
            announce(f"flatserve: preparing the demo light field {name!r}; viewer: {url}")
            ensure_demo_field(registry, name, n)
            announce(f"flatserve: demo field {name!r} ready - open {url}")
        except Exception:  # the server keeps serving; the log says why
            log.exception("demo field %r could not be built", name)

    th = threading.Thread(target=run, name="flatserve-demo", daemon=True)
    th.start()
    return th
