"""Fixtures for the service tests: apps on temporary data dirs, a started app, the
generator of random numbers. The helpers the tests share are in tests/harness/
(:mod:`tests.harness.fields`: the kinds of field and the paper's rays;
:mod:`tests.harness.service`: apps started in-process, uploads under kill -9 and
their check)."""
from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.client import Client
from flatserve.service import Settings, create_app


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
