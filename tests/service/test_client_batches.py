"""The client against the server's limits: uploads and queries split at the limits
the server publishes (``GET /v1/limits``), one Idempotency-Key per batch (a repeated
call stores nothing twice and loses nothing), progress, ``create_field(exist_ok=)``,
retries on 429 / 503 after ``Retry-After``."""
from __future__ import annotations

import time

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.client import Client
from flatserve.errors import InvalidInputError
from flatserve.service.status import FieldExistsError, NotReadyError
from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.service import started


def _server(make_app, tmp_path, name, **settings):
    return started(make_app(data_dir=tmp_path / name, **settings))


@pytest.fixture
def two(make_app, tmp_path):
    """``(limited, unlimited)`` clients: a server taking at most 100 rows a request
    and one with the default limits, each on its own data directory."""
    servers = [_server(make_app, tmp_path, "small", max_batch_rows=100),
               _server(make_app, tmp_path, "big")]
    yield servers[0][1], servers[1][1]
    for tc, _ in servers:
        tc.__exit__(None, None, None)


def test_limits_endpoint_states_the_settings(make_app):
    with TestClient(make_app(max_batch_rows=123, max_body_bytes=45_678), base_url="http://127.0.0.1") as tc:
        lim = tc.get("/v1/limits").json()
    assert lim["max_batch_rows"] == 123 and lim["max_body_bytes"] == 45_678
    assert {"max_json_bytes", "max_pending_samples"} <= set(lim)


@pytest.mark.parametrize("binary", [True, False])
def test_upload_and_query_past_the_limit_answer_as_one_request(two, rng, binary):
    small, big = two
    n = 350
    o, v = paper_rays(rng, n)
    val = rng.uniform(size=(n, 2))
    v[::7] = [1.0, 0.0, 0.05]  # outside the chart: rejected rows, numbered in the whole upload
    for c in (small, big):
        c.create_field("f", channels=2, basis=ONE_CHART)
    whole = big.upload_rays("f", o, v, val, binary=binary)
    split = small.upload_rays("f", o, v, val, binary=binary)
    assert len(split["batches"]) == 4 and "batches" not in whole
    assert [b["rows"] for b in small.batches("f")] == [100, 100, 100, 50]
    assert split["accepted"] == whole["accepted"]
    assert split["rejected"] == whole["rejected"]
    assert set(range(0, n, 7)) <= set(split["rejected"])
    assert split["reasons"] == whole["reasons"]
    assert split["nsamples"] == whole["nsamples"] and split["indexed"]
    # a Delaunay triangulation does not depend on the order of insertion: same answers
    qo, qv = paper_rays(rng, 250)
    a = small.query_rays("f", qo, qv, binary=binary)
    b = big.query_rays("f", qo, qv, binary=binary)
    assert a.values.shape == (250, 2) and a.inside.sum() > 200
    np.testing.assert_array_equal(a.inside, b.inside)
    np.testing.assert_allclose(a.values, b.values, rtol=1e-12, atol=1e-14)


def test_body_limit_splits_too(make_app, tmp_path, rng):
    # 20 kB bodies hold 20_000 // (8 * 7) = 357 rows (less the overhead) of rays + 1 value
    tc, c = _server(make_app, tmp_path, "d", max_body_bytes=20_000)
    try:
        c.create_field("f", basis=ONE_CHART)
        o, v = paper_rays(rng, 1000)
        rep = c.upload_rays("f", o, v, rng.uniform(size=1000))
        rows = [b["rows"] for b in c.batches("f")]
        assert sum(rows) == 1000 and len(rows) == len(rep["batches"]) > 2
        assert max(rows) * 8 * 7 + 128 <= 20_000
        assert c.query_rays("f", o, v).values.shape == (1000, 1)
    finally:
        tc.__exit__(None, None, None)


def test_a_repeated_split_upload_stores_what_was_missing_and_nothing_twice(two, rng):
    small, _ = two
    small.create_field("f", basis=ONE_CHART)
    o, v = paper_rays(rng, 420)
    val = rng.uniform(size=420)

    class Died(Exception):
        pass

    def die_after_two(done, total):
        if done >= 200:
            raise Died  # the client dies after the second batch

    with pytest.raises(Died):
        small.upload_rays("f", o, v, val, idempotency_key="load-1", progress=die_after_two)
    assert [b["idempotency_key"] for b in small.batches("f")] == ["load-1.0", "load-1.1"]
    rep = small.upload_rays("f", o, v, val, idempotency_key="load-1")
    stored = small.batches("f")
    assert [b["idempotency_key"] for b in stored] == [f"load-1.{i}" for i in range(5)]
    assert sum(b["rows"] for b in stored) == 420 and not rep["replayed"]
    assert small.describe("f")["nsamples"] == rep["nsamples"] == rep["accepted"]
    again = small.upload_rays("f", o, v, val, idempotency_key="load-1")
    assert again["replayed"] and len(small.batches("f")) == 5
    # the same key with another split sends other rows under a key: refused, not stored
    with pytest.raises(InvalidInputError, match="different batch"):
        small.upload_rays("f", o, v, val, idempotency_key="load-1", batch_rows=70)
    assert len(small.batches("f")) == 5


def test_progress_callback_and_bar(two, rng, capsys):
    small, big = two
    big.create_field("f", basis=ONE_CHART)
    o, v = paper_rays(rng, 25_000)
    seen = []
    rep = big.upload_rays("f", o, v, rng.uniform(size=25_000), wait=False,
                          progress=lambda done, total: seen.append((done, total)))
    # a progress bar without batch_rows: batches of at least 10,000 rows
    assert seen == [(10_000, 25_000), (20_000, 25_000), (25_000, 25_000)]
    assert len(rep["batches"]) == 3
    small.create_field("g", basis=ONE_CHART)
    small.upload_rays("g", o[:300], v[:300], np.ones(300), progress=True)
    err = capsys.readouterr().err
    assert "upload g" in err and "300/300" in err


def test_create_field_exist_ok(api):
    _, c = api
    first = c.create_field("f", channels=3)
    with pytest.raises(FieldExistsError):
        c.create_field("f", channels=3)
    again = c.create_field("f", channels=3, exist_ok=True)
    assert again["name"] == "f" and again["created"] == first["created"]
    with pytest.raises(FieldExistsError, match="channels=3 .asked 1."):
        c.create_field("f", channels=1, exist_ok=True)
    with pytest.raises(FieldExistsError, match="oriented"):
        c.create_field("f", channels=3, oriented=True, exist_ok=True)


def _scripted(answers: list[httpx.Response]):
    """An httpx client answering ``answers`` in turn, and the list of requests it got."""
    got = []

    def handler(request):
        got.append((request.method, request.url.path))
        return answers[len(got) - 1]

    return httpx.Client(base_url="http://127.0.0.1:1", transport=httpx.MockTransport(handler)), got


def test_idempotent_requests_are_retried_after_retry_after():
    busy = httpx.Response(503, headers={"Retry-After": "0.3"}, json={"detail": "loading"})
    full = httpx.Response(429, headers={"Retry-After": "0.2"}, json={"detail": "backlog"})
    ok = httpx.Response(200, json={"name": "f"})
    http, got = _scripted([busy, full, ok])
    c = Client(http=http, retries=2)
    t0 = time.monotonic()
    assert c.describe("f") == {"name": "f"}
    assert time.monotonic() - t0 >= 0.5 and len(got) == 3
    # out of retries: the error of the last answer
    http, got = _scripted([busy, busy])
    with pytest.raises(NotReadyError):
        Client(http=http, retries=1).describe("f")
    assert len(got) == 2
    # a create is not idempotent: never retried
    http, got = _scripted([busy, ok])
    with pytest.raises(NotReadyError):
        Client(http=http, retries=2).create_field("f")
    assert got == [("POST", "/v1/fields")]
    # Retry-After is capped
    http, got = _scripted([httpx.Response(503, headers={"Retry-After": "3600"}), ok])
    t0 = time.monotonic()
    Client(http=http, retries=1, max_retry_after=0.1).describe("f")
    assert time.monotonic() - t0 < 5
