"""Fixtures for the service tests: apps on temporary data dirs, ray batches."""
from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.client import Client
from flatserve.service import Settings, create_app


def paper_rays(rng: np.random.Generator, n: int):
    """The paper's ray set-up: eyes in [-1,1]^2 x [-4.5,-1.5] towards the screen z = 0."""
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def started(app):
    """Enter ``app``'s lifespan (the caller exits it) and wait until it is ready."""
    tc = TestClient(app)
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
    with TestClient(make_app()) as tc:
        tc.get("/readyz")
        c = Client(http=tc)
        c.wait_ready(30)
        yield tc, c
