"""The smaller findings of an adversarial probe, one test each: what /readyz and
storage errors tell a client without a key, OpenAPI and server agreeing, the lean
query path's pattern, repeated Idempotency-Key headers, the SQLite snapshot lease
after its holder died, and linear algebra that does not converge."""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.service.http import errors
from flatserve.service.log.sqlrules import Failure, storage_failure
from tests.harness.fields import paper_rays
from tests.harness.service import started

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


@pytest.mark.parametrize("suffix", ["%0A", "%0D", "%00", "%0A%0A"])
def test_paths_with_control_characters_are_404(api, rng, suffix):
    """``/v1/fields/f/query%0A`` is no route (Python's ``$`` matches before a final
    newline, in the lean path's pattern and in Starlette's): 404, like
    ``/v1/fields/f/samples%0A``."""
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 3)
    body = {"origins": o.tolist(), "directions": v.tolist()}
    assert tc.post("/v1/fields/f/query", json=body).status_code == 200
    for path in ("/v1/fields/f/query", "/v1/fields/f/samples", "/v1/fields/f", "/healthz"):
        r = tc.post(path + suffix, json=body)
        assert r.status_code == 404, (path, r.status_code, r.text)


def test_lean_path_pattern_matches_whole_paths():
    from flatserve.service.http.fastpath import _PATH

    assert _PATH.fullmatch("/v1/fields/abc/query")
    assert not _PATH.fullmatch("/v1/fields/abc/query\n")


def test_repeated_idempotency_key_is_400(api, rng):
    """A repeated ``Idempotency-Key`` is refused as a repeated ``api-key`` is: proxies
    disagree on which copy counts. Nothing is stored."""
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 5)
    body = {"origins": o.tolist(), "directions": v.tolist(), "values": np.ones((5, 1)).tolist()}
    r = tc.post("/v1/fields/f/samples", json=body,
                headers=[("idempotency-key", "a"), ("idempotency-key", "b")])
    assert r.status_code == 400 and "idempotency-key header is repeated" in r.text, r.text
    assert c.describe("f")["storage"]["batches"] == 0
    r = tc.post("/v1/fields/f/samples", json=body, headers={"idempotency-key": "a"})
    assert r.status_code == 200


def test_a_killed_unreaped_lease_owner_is_dead():
    """kill -9 of the replica writing a snapshot leaves a zombie until its supervisor
    reaps it; ``kill(pid, 0)`` succeeds on a zombie, yet its lease is taken over."""
    import os
    import signal
    import socket
    import subprocess
    import sys
    import time

    from flatserve.service.log.datadir import owner_dead

    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    owner = f"{socket.gethostname()}:{p.pid}:abcd1234"
    try:
        assert not owner_dead(owner)
        os.kill(p.pid, signal.SIGKILL)
        end = time.monotonic() + 10
        while time.monotonic() < end:  # until the kernel has made it a zombie
            with open(f"/proc/{p.pid}/stat", "rb") as fh:
                if fh.read().rpartition(b")")[2].split()[0] == b"Z":
                    break
            time.sleep(0.01)
        os.kill(p.pid, 0)  # still "exists": a zombie, not reaped
        assert owner_dead(owner)
    finally:
        p.kill()
        p.wait()
    assert owner_dead(owner)
    assert not owner_dead(f"{socket.gethostname()}:{os.getpid()}:x")


def test_entries_near_the_float64_limit_are_refused_at_the_boundary(api):
    """Flats with entries near the float64 limit overflow in their products (LAPACK
    then fails on the whole batch: "Eigenvalues did not converge", "SVD did not
    converge"); they are refused when the flats are validated, naming the array."""
    tc, c = api
    big = 1.7e308
    body = {"k": 0, "d": 2, "flats": {"Q": [[[big, big], [big, big]], [[-big, -big], [-big, -big]]],
                                      "r": [[0, 0], [0, 0]]},
            "weights": [[2.0, -1.0], [0.5, 0.5]]}
    r = tc.post("/v1/math/project", json=body)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"][-1] == "Q" and d["type"] == "InvalidInputError", d
    assert "entries beyond" in d["msg"] and "rows [0, 1]" in d["msg"]
    c.create_field("f", channels=1)
    o = [[1.7e308, -1.7e308, 1.7e308], [0.0, 0.0, -3.0]]
    for path, extra in (("/v1/fields/f/samples", {"values": [[1.0], [2.0]]}),
                        ("/v1/fields/f/query", {})):
        r = tc.post(path, json={"origins": o, "directions": [[0, 0, 1], [0, 0, 1]], **extra})
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["loc"][-1] == "origins", r.text
    assert c.describe("f")["storage"]["batches"] == 0


def test_eigendecomposition_not_converging_is_a_validation_error(api, monkeypatch):
    """LAPACK's "Eigenvalues did not converge" (LinAlgError, a ValueError) is turned
    into the library's InvalidInputError naming the argument, not left to the
    service's catch-all for ValueError."""
    tc, _ = api

    def fails(a, *args, **kw):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    monkeypatch.setattr(np.linalg, "eigh", fails)
    body = {"k": 0, "d": 2, "flats": {"Q": [np.eye(2).tolist()] * 2, "r": [[0, 0], [1, 0]]},
            "weights": [[0.5, 0.5]]}
    r = tc.post("/v1/math/project", json=body)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"] == ["body", "weights"] and d["type"] == "InvalidInputError", d


def test_large_entries_within_the_bound_are_charted_row_by_row(rng):
    """Entries up to the bound (flatserve.flats.MAX_ENTRY) are charted: a far row fails
    its round trip alone (a status), the batch's other rows are unaffected."""
    import flatserve
    from flatserve.flats import MAX_ENTRY, Flats

    basis = flatserve.Basis.around_axis(axis=3, d=4, scale=0.01)
    o, v = rng.normal(size=(4, 4)), rng.normal(size=(4, 4))
    v[:, 3] = 5.0
    alone = basis.coordinates_of(Flats.from_rays(o, v))
    o[1] = [MAX_ENTRY, -MAX_ENTRY, MAX_ENTRY, MAX_ENTRY]
    c = basis.coordinates_of(Flats.from_rays(o, v))
    keep = [0, 2, 3]
    np.testing.assert_array_equal(np.asarray(c.status)[keep], np.asarray(alone.status)[keep])
    np.testing.assert_array_equal(c.weights[keep], alone.weights[keep])
    assert np.asarray(c.status)[1] != 0


@pytest.mark.parametrize("flats", [{}, {"origins": None, "directions": None, "Q": None, "r": None,
                                        "A": None, "b": None}, {"Q": None, "r": None}])
def test_flats_without_arrays_are_outside_the_schema_and_refused(api, flats):
    """The documented schema of a batch of flats requires one pair of arrays (both
    given, not null), as the server does: a body the schema allows is not refused
    for want of arrays, and one it refuses gets a 422 naming ``flats``."""
    import jsonschema_rs  # schemathesis' own validator

    tc, _ = api
    doc = tc.get("/openapi.json").json()
    schema = {**doc["components"]["schemas"]["FlatsModel"], "components": doc["components"]}
    valid = jsonschema_rs.Draft202012Validator(schema).is_valid
    assert not valid(flats)
    body = {"k": 1, "d": 3, "basis": {"kind": "tangent_simplex"}, "flats": flats}
    r = tc.post("/v1/math/coordinates", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][:2] == ["body", "flats"], r.text
    ok = {"origins": [[0, 0, -3]], "directions": [[0, 0, 1]]}
    assert valid(ok)
    assert tc.post("/v1/math/coordinates", json={**body, "flats": ok}).status_code == 200


def test_min_position_beyond_the_head_is_located_in_the_query(api, rng):
    tc, c = api
    c.create_field("f", channels=1)
    o, v = paper_rays(rng, 2)
    for r in (tc.post("/v1/fields/f/query", params={"min_position": 10**9},
                      json={"origins": o.tolist(), "directions": v.tolist()}),
              tc.get("/v1/fields/f", params={"min_position": 10**9})):
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["loc"] == ["query", "min_position"], r.text


@pytest.mark.parametrize("method, path, allow", [
    ("PUT", "/v1/fields/f", "DELETE, GET"),
    ("PATCH", "/v1/fields", "GET, POST"),
    ("GET", "/v1/fields/f/samples", "POST"),
    ("POST", "/openapi.json", "GET, HEAD"),
])
def test_405_allow_lists_every_method_of_the_path(api, method, path, allow):
    tc, c = api
    c.create_field("f", channels=1)
    r = tc.request(method, path)
    assert r.status_code == 405
    assert r.headers["allow"] == allow


@pytest.mark.parametrize("member", [{"fill": False}, {"focal": True}, {"width": True},
                                    {"orbit": {"yaw": False}}, {"fill": "0"}])
def test_render_takes_numbers_only(api, member):
    tc, c = api
    c.create_field("f", channels=1)
    r = tc.post("/v1/fields/f/render", json={"width": 4, "height": 4, "supersample": 1, **member})
    assert r.status_code == 422, r.text
    r = tc.post("/v1/fields/f/render", json={"width": 4, "height": 4, "supersample": 1,
                                             "fill": 0, "focal": 2})
    assert r.status_code == 200, r.text
