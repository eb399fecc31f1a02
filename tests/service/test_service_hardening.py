"""The smaller findings of an adversarial probe, one test each: what /readyz and
storage errors tell a client without a key, OpenAPI and server agreeing, the lean
query path's pattern, repeated Idempotency-Key headers, the SQLite snapshot lease
after its holder died, and linear algebra that does not converge."""
from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.service import errors
from flatserve.service.sqlrules import Failure, storage_failure

from .conftest import paper_rays, started

LOCAL = "http://127.0.0.1"
RO, RW = {"api-key": "ro"}, {"api-key": "rw"}


def test_readyz_is_the_status_alone_without_a_key(make_app):
    """Keys on: /readyz answers anyone, with the status only; the details (pid,
    backend, positions, the fields loading or failed) need the read key."""
    tc, c = started(make_app(api_key="rw", read_only_key="ro"))
    try:
        tc.post("/v1/fields", json={"name": "secret-name", "channels": 1}, headers=RW)
        for headers in ({}, {"api-key": "wrong"}, [("api-key", "ro"), ("api-key", "ro")]):
            r = tc.get("/readyz", headers=headers)
            assert r.status_code == 200
            assert r.json() == {"status": "ready"}, r.text
        for key in (RO, RW):
            body = tc.get("/readyz", headers=key).json()
            assert body["status"] == "ready" and body["fields"] == 1
            assert {"pid", "backend", "position", "head"} <= set(body)
    finally:
        tc.__exit__(None, None, None)


def test_readyz_details_without_keys_configured(api):
    """Keys off (loopback): every caller may read, so /readyz gives the details."""
    tc, _ = api
    assert "pid" in tc.get("/readyz").json()


def test_storage_failures_tell_clients_neither_where_nor_the_database_message():
    """507 / 503 bodies carry the failure's public text; the host, user, database
    and relation paths stay in the exception's own text, for the log."""
    where = "db.internal:5432/flatserve as flatserve_owner"
    driver = 'could not extend file "base/16384/16402": No space left on device'
    for kind, status in ((Failure.FULL, 507), (Failure.UNREACHABLE, 503),
                         (Failure.FAILED, 503), (Failure.DAMAGED, 503)):
        exc = storage_failure(kind, Exception(driver), where)
        assert where in str(exc) and "16402" in str(exc)
        resp = errors.error_response(exc)
        assert resp.status_code == status
        text = resp.body.decode()
        for secret in ("db.internal", "flatserve_owner", "16384", "16402", "5432"):
            assert secret not in text, (kind, text)
