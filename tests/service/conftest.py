"""Fixtures for the service tests: apps on temporary data dirs, ray batches, the
kinds of field (the default covering atlas, the paper's single chart) with the
library field that must answer the same."""
from __future__ import annotations

import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.client import Client
from flatserve.field import Field
from flatserve.flats import Flats
from flatserve.service import Settings, create_app, specs
from flatserve.service.schemas import TangentSimplexBasis

#: The paper's single chart: the tangent simplex around the z-axis, scale 0.01.
ONE_CHART = {"kind": "tangent_simplex"}


@dataclass(frozen=True)
class Kind:
    """A kind of field over HTTP and the library field that answers the same.

    Attributes
    ----------
    name : str
    basis : dict or None
        The create request's ``basis``; None: the default (a covering atlas).
    """

    name: str
    basis: dict | None

    @property
    def atlas(self) -> bool:
        """The field blends charts: every orientation accepted, no ``weights=true``."""
        return self.basis is None

    def reference(self, channels: int, k: int = 1, d: int = 3) -> "Field | AtlasField":
        """An empty library field built as the service builds this kind."""
        if self.atlas:
            return AtlasField(Atlas.covering(k, d, unit="fit"), channels=channels)  # unit: fit
        return Field(specs.build_basis(TangentSimplexBasis(**self.basis), k, d),
                     channels=channels)

    def __str__(self) -> str:
        return self.name


DEFAULT = Kind("default-atlas", None)
SINGLE = Kind("one-chart", ONE_CHART)
#: Both kinds, for tests of what must hold whatever the basis.
KINDS = [DEFAULT, SINGLE]


def add_rays(ref, o, v, values):
    """``ref.add`` of rays, for a Field or an AtlasField."""
    return ref.add(Flats.from_rays(o, v), values)


def query_rays(ref, o, v, **kw):
    """``ref.query`` of rays, for a Field or an AtlasField."""
    return ref.query(Flats.from_rays(o, v), **kw)


def paper_rays(rng: np.random.Generator, n: int):
    """The paper's ray set-up: eyes in [-1,1]^2 x [-4.5,-1.5] towards the screen z = 0."""
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def upload_until_stopped(url, field, tag, rng, sent, acked, stop, *, max_rows, binary_every,
                         survive=False):
    """Upload random batches of paper rays to ``field`` until ``stop`` is set.

    Each batch's rays go into ``sent[key]`` before it is sent and its answer into
    ``acked[key]`` once acknowledged (``key`` is ``f"{tag}-b{i}"``, also the
    Idempotency-Key); every other batch is acknowledged before it is indexed
    (wait=false), one in ``binary_every`` goes as JSON. When the server dies under
    it, the uploader returns, or with ``survive`` pauses and goes on (a sibling
    replica behind the same URL).
    """
    c = Client(url, retries=0, timeout=30)
    i = 0
    try:
        while not stop.is_set():
            n = int(rng.integers(20, max_rows))
            o, v = paper_rays(rng, n)
            val = rng.uniform(size=(n, 1))
            key = f"{tag}-b{i}"
            sent[key] = (o, v, val)
            try:
                acked[key] = c.upload_rays(field, o, v, val, idempotency_key=key,
                                           binary=bool(i % binary_every), wait=bool(i % 2))
            except Exception:
                if stop.is_set() or not survive:
                    return
                time.sleep(0.05)
            i += 1
    finally:
        c.close()


def save_bytes(data: bytes):
    """A snapshot writer for ``LogBackend.write_snapshot`` (``save(path, stage)``)
    that writes ``data`` and names no parts."""
    def save(path, stage):
        with open(path, "wb") as fh:
            fh.write(data)
    return save


def assert_data_dir_refused(data, holder_pid):
    """A second server started on ``data`` exits with 2, naming the holder's pid."""
    out = subprocess.run([sys.executable, "-m", "flatserve.service", "--port", "1",
                          "--data-dir", str(data)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "in use by another flatserve server" in out.stderr, out.stderr
    assert f"pid {holder_pid}" in out.stderr


@contextmanager
def running(app):
    """``(TestClient, Client)`` of ``app`` started and ready (:func:`started`), its
    lifespan exited at the end of the block."""
    tc, c = started(app)
    try:
        yield tc, c
    finally:
        tc.__exit__(None, None, None)


def started(app):
    """Enter ``app``'s lifespan (the caller exits it) and wait until it is ready."""
    tc = TestClient(base_url="http://127.0.0.1", app=app)
    tc.__enter__()
    c = Client(http=tc)
    c.wait_ready(60)
    return tc, c


@pytest.fixture
def rng():
    return np.random.default_rng(20240531)


@pytest.fixture
def make_app(tmp_path):
    """``make_app(**settings) -> FastAPI`` on a temporary data dir (shared per test)."""

    def make(**kw):
        kw.setdefault("data_dir", tmp_path / "data")
        kw.setdefault("snapshot_every", 0)
        return create_app(Settings(**kw))

    return make


@pytest.fixture
def api(make_app):
    """A started app: ``(TestClient, flatserve Client)``."""
    with TestClient(base_url="http://127.0.0.1", app=make_app()) as tc:
        tc.get("/readyz")
        c = Client(http=tc)
        c.wait_ready(30)
        yield tc, c
