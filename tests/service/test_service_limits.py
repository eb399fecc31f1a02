"""Limits that keep one client or one field from holding up the server: the body
limit on chunked bodies, the wait=false backlog, the cost guard of high-dimensional
fields, repeated key headers, strict JSON, and fields that restore independently."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from flatserve.service.rooms import applier as applier_mod
from tests.harness.fields import KINDS, paper_rays
from tests.harness.process import ServerProcess
from tests.harness.service import started


def _chunks(total: int, size: int = 65536):
    sent = 0
    while sent < total:
        n = min(size, total - sent)
        sent += n
        yield b" " * n


@pytest.mark.parametrize("path", ["/v1/fields", "/v1/math/coordinates",
                                  "/v1/fields/f/query", "/v1/fields/f/samples",
                                  "/v1/fields/f/render"])
def test_chunked_body_past_the_limit_is_413_on_every_route(make_app, path):
    tc, c = started(make_app(max_body_bytes=100_000))
    try:
        c.create_field("f", channels=1)
        # a generator body is sent with Transfer-Encoding: chunked (no Content-Length)
        r = tc.post(path, content=_chunks(1_000_000), headers={"Content-Type": "application/json"})
        assert r.status_code == 413, (path, r.status_code, r.text)
        assert "limit of 100000 bytes" in r.text
        assert tc.get("/healthz").status_code == 200
    finally:
        tc.__exit__(None, None, None)


def test_wait_false_backlog_is_bounded_with_429(make_app, rng, monkeypatch):
    gate = threading.Event()
    monkeypatch.setattr(applier_mod.LogApplier, "_before_index",
                        staticmethod(lambda e, seq: gate.wait(30)))
    tc, c = started(make_app(max_pending_samples=500))
    try:
        c.create_field("f", channels=1)
        o, v = paper_rays(rng, 1200)
        first = c.upload_rays("f", o[:400], v[:400], np.ones(400), wait=False)
        assert not first["indexed"]
        r = tc.post("/v1/fields/f/samples", params={"wait": "false"},
                    json={"origins": o[400:800].tolist(), "directions": v[400:800].tolist(),
                          "values": np.ones((400, 1)).tolist()})
        assert r.status_code == 429 and r.headers["retry-after"] == "1", r.text
        assert "FLATSERVE_MAX_PENDING_SAMPLES" in r.text
        info = c.describe("f")  # describe never waits for the indexer
        assert info["pending_batches"] == 1 and info["storage"]["batches"] == 1
        gate.set()
        c.wait_indexed("f", timeout=30)
        assert c.upload_rays("f", o[400:800], v[400:800], np.ones(400), wait=False)["batch"] == 2
    finally:
        gate.set()
        tc.__exit__(None, None, None)


def test_high_dimensional_field_is_refused_before_it_explodes(make_app, rng):
    tc, c = started(make_app(max_simplices=100_000, min_field_samples=0))  # the upload guard
    try:
        c.create_field("p8", k=0, d=8, channels=1)  # points in R^8: an 8-D triangulation
        pts = rng.normal(size=(200, 8))
        Q = np.broadcast_to(np.eye(8), (200, 8, 8))
        r = tc.post("/v1/fields/p8/samples", json={"Q": Q.tolist(), "r": pts.tolist(),
                                                   "values": np.ones((200, 1)).tolist()})
        assert r.status_code == 413, r.text
        assert "cells expected" in r.text and "FLATSERVE_MAX_SIMPLICES" in r.text
        assert c.describe("p8")["storage"]["batches"] == 0
        small = tc.post("/v1/fields/p8/samples", json={
            "Q": Q[:12].tolist(), "r": pts[:12].tolist(), "values": np.ones((12, 1)).tolist()})
        assert small.status_code == 200, small.text
    finally:
        tc.__exit__(None, None, None)


def test_repeated_key_headers_are_refused(make_app):
    tc, c = started(make_app(api_key="rw", read_only_key="ro"))
    try:
        for path in ("/v1/fields", "/v1/fields/x/query"):
            method = tc.get if path == "/v1/fields" else tc.post
            r = method(path, headers=[("api-key", "ro"), ("api-key", "rw")])
            assert r.status_code == 400 and "repeated" in r.text, (path, r.text)
    finally:
        tc.__exit__(None, None, None)



def test_two_different_keys_are_refused_the_same_in_both_accepted(make_app):
    """``api-key`` and ``Authorization: Bearer`` with different keys are a 400 naming
    both headers, on every route (the read-only Bearer beside the read-write
    ``api-key`` wrote); the same key in both, or ``api-key`` beside an
    ``Authorization`` of another scheme, is that key."""
    tc, c = started(make_app(api_key="rw", read_only_key="ro"))

    def keys(api_key, bearer):
        return {"api-key": api_key, "Authorization": f"Bearer {bearer}"}

    try:
        for path, method in (("/v1/fields", tc.get), ("/v1/fields/x/query", tc.post),
                             ("/v1/fields/x/render", tc.post), ("/v1/fields", tc.post)):
            for headers in (keys("rw", "ro"), keys("ro", "rw"), keys("rw", "wrong")):
                r = method(path, headers=headers)
                assert r.status_code == 400, (path, headers, r.status_code, r.text)
                assert "api-key" in r.text and "Authorization" in r.text, r.text
        spec = {"name": "f", "k": 1, "d": 3, "channels": 1}
        assert tc.post("/v1/fields", json=spec, headers=keys("rw", "ro")).status_code == 400
        assert tc.post("/v1/fields", json=spec, headers=keys("rw", "rw")).status_code == 201
        assert tc.get("/v1/fields", headers=keys("ro", "ro")).json()["fields"][0]["name"] == "f"
        assert tc.post("/v1/fields", json={**spec, "name": "g"},
                       headers=keys("ro", "ro")).status_code == 403
        r = tc.post("/v1/fields", json={**spec, "name": "g"},
                    headers={"api-key": "rw", "Authorization": "Basic dXNlcjpwdw=="})
        assert r.status_code == 201, r.text
    finally:
        tc.__exit__(None, None, None)

@pytest.mark.parametrize("body, member", [
    ({"origins": [[0, 0, -3]], "directions": [[0, 0, 1]], "Q": [np.eye(3).tolist()]}, "body"),
    ({"origins": [[0, 0, -3]], "directions": [[0, 0, 1]], "extra": 1}, "extra"),
    ({"origins": [["0", 0, -3]], "directions": [[0, 0, 1]]}, "origins"),
    ({"origins": [[True, 0, -3]], "directions": [[0, 0, 1]]}, "origins"),
    ({"origins": [[0.5, 0, -3]], "directions": [[0, False, 1]]}, "directions"),
])
def test_ambiguous_json_bodies_are_422(api, body, member):
    tc, c = api
    c.create_field("f")
    r = tc.post("/v1/fields/f/query", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == member, r.text


def test_strings_for_numbers_in_field_specs_are_422(api):
    tc, _ = api
    r = tc.post("/v1/fields", json={"name": "s", "basis": {"scale": "0.02"}})
    assert r.status_code == 422, r.text
    r = tc.post("/v1/fields", json={"name": "s", "k": True})
    assert r.status_code == 422, r.text


def test_fields_restore_independently(make_app, rng, monkeypatch):
    tc, c = started(make_app())
    try:
        for name in ("slow", "quick"):
            c.create_field(name, channels=1)
            o, v = paper_rays(rng, 300)
            c.upload_rays(name, o, v, np.ones(300))
    finally:
        tc.__exit__(None, None, None)
    gate = threading.Event()
    real = applier_mod.LogApplier._restore

    def restore(self, e, row):
        if e.name == "slow":
            gate.wait(30)
        return real(self, e, row)

    monkeypatch.setattr(applier_mod.LogApplier, "_restore", restore)
    from fastapi.testclient import TestClient
    from flatserve.client import Client

    with TestClient(base_url="http://127.0.0.1", app=make_app()) as tc:
        c = Client(http=tc)
        from flatserve.service.status import NotReadyError

        for _ in range(400):  # the quick field answers while the slow one loads
            try:
                if c.describe("quick")["state"] == "ready":
                    break
            except NotReadyError:  # the stored fields are not even registered yet
                pass
            threading.Event().wait(0.02)
        o, v = paper_rays(rng, 5)
        assert c.query_rays("quick", o, v).values.shape == (5, 1)
        ready = tc.get("/readyz")
        assert ready.status_code == 503 and ready.json()["loading_fields"] == ["slow"]
        assert tc.post("/v1/fields/slow/query", json={"origins": o.tolist(),
                                                      "directions": v.tolist()}).status_code == 503
        gate.set()
        c.wait_ready(30)
        assert tc.get("/readyz").json()["loading_fields"] == []


def test_big_json_bodies_do_not_stall_the_event_loop(tmp_path, rng):
    """Decoding and validating big bodies happens off the event loop: /healthz keeps
    answering within a second while a 6 MiB JSON query and a JSON math document are
    parsed; JSON beyond max_json_bytes is refused at once (bulk arrays go as .npy)."""
    import json as _json

    import httpx

    with ServerProcess(tmp_path / "data", tmp_path / "server.log") as srv:
        srv.wait_ready()
        httpx.post(srv.url + "/v1/fields", json={"name": "f"}).raise_for_status()
        o, v = paper_rays(rng, 50_000)
        bodies = [("/v1/fields/f/query", {"origins": o.tolist(), "directions": v.tolist()}),
                  ("/v1/math/coordinates", {"flats": {"origins": o.tolist(),
                                                      "directions": v.tolist()}})]
        for path, obj in bodies:
            body = _json.dumps(obj).encode()
            assert 4 << 20 < len(body) < 8 << 20  # under the default max_json_bytes
            lat, stop = [], threading.Event()

            def ping():
                with httpx.Client(base_url=srv.url) as c:
                    while not stop.is_set():
                        t = time.perf_counter()
                        c.get("/healthz", timeout=30).raise_for_status()
                        lat.append(time.perf_counter() - t)
                        time.sleep(0.01)

            th = threading.Thread(target=ping)
            th.start()
            try:
                r = httpx.post(srv.url + path, content=body, timeout=120,
                               headers={"Content-Type": "application/json"})
            finally:
                stop.set()
                th.join()
            assert r.status_code == 200, r.text
            assert lat and max(lat) < 1.0, (path, max(lat))  # pinged throughout the request
        big = _json.dumps({"origins": [[0.0, 0.0, -3.0]] * 900_000,
                           "directions": [[0.0, 0.0, 1.0]] * 900_000}).encode()
        r = httpx.post(srv.url + "/v1/fields/f/query", content=big, timeout=60,
                       headers={"Content-Type": "application/json"})
        assert r.status_code == 413 and "FLATSERVE_MAX_JSON_BYTES" in r.text


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_reads_keep_flowing_while_a_big_wait_false_batch_is_indexed(make_app, rng, kind):
    """The indexer inserts a wait=false batch in slices (an atlas field's chart by
    chart): queries answer between slices instead of waiting for the whole insert."""
    tc, c = started(make_app(insert_slice_rows=2_000))
    try:
        c.create_field("f", channels=1, basis=kind.basis)
        o, v = paper_rays(rng, 2000)
        c.upload_rays("f", o, v, np.ones(2000))
        probe = paper_rays(rng, 4)
        big = paper_rays(rng, 40_000)
        lat, stop = [], threading.Event()

        def reads():
            while not stop.is_set():
                t = time.perf_counter()
                c.query_rays("f", *probe)
                lat.append(time.perf_counter() - t)

        th = threading.Thread(target=reads)
        th.start()
        t0 = time.perf_counter()
        rep = c.upload_rays("f", *big, np.ones(40_000), wait=False)
        c.wait_indexed("f", timeout=120, interval=0.005)
        indexing = time.perf_counter() - t0
        stop.set()
        th.join()
        assert not rep["indexed"] and c.describe("f")["nsamples"] > 30_000
        # about 18 slices: no read waits for more than a few of them
        assert len(lat) > 10 and max(lat) < indexing / 3, (max(lat), indexing, len(lat))
    finally:
        tc.__exit__(None, None, None)


def test_failed_insert_after_the_commit_is_a_503_and_the_retry_gets_the_batch(
        make_app, rng, monkeypatch):
    """A wait=true batch is committed before it is inserted: if the insert fails, the
    client is told the batch is stored (503, not 500), the field is rebuilt from
    storage, and a retry with the same key gets the batch's response, indexed."""
    from flatserve.field import Field

    tc, c = started(make_app())
    try:
        c.create_field("f", channels=1, unit="data")  # (no fit: its fields insert too)
        o, v = paper_rays(rng, 300)
        real, calls = Field.insert_prepared, []

        def fails_once(self, batch, **kw):
            calls.append(1)
            if len(calls) == 1:
                raise MemoryError("simulated")
            return real(self, batch, **kw)

        monkeypatch.setattr(Field, "insert_prepared", fails_once)
        r = tc.post("/v1/fields/f/samples", headers={"Idempotency-Key": "k"},
                    json={"origins": o.tolist(), "directions": v.tolist(),
                          "values": np.ones((300, 1)).tolist()})
        assert r.status_code == 503 and "batch 1 is stored" in r.text, r.text
        assert r.headers["retry-after"] == "1"
        c.wait_ready(30)
        for _ in range(400):  # the rebuild from storage
            if c.describe("f")["state"] == "ready":
                break
            time.sleep(0.02)
        again = c.upload_rays("f", o, v, np.ones(300), idempotency_key="k")
        assert again["replayed"] and again["indexed"] and again["batch"] == 1
        info = c.describe("f")
        assert info["storage"]["batches"] == 1 and info["nsamples"] == again["accepted"]
    finally:
        tc.__exit__(None, None, None)


def test_out_of_memory_before_the_commit_is_a_503_and_nothing_is_stored(
        make_app, rng, monkeypatch):
    """A MemoryError while an upload is charted (before its commit) or while a query
    runs: a 503 with Retry-After that says so, not a 500; nothing of the upload is
    stored, and the same request succeeds once memory is there."""
    from flatserve.field import Field

    tc, c = started(make_app())
    try:
        c.create_field("f", channels=1, unit="data")
        o, v = paper_rays(rng, 300)
        real_prepare, real_query = Field.prepare, Field.query

        def no_memory(*a, **kw):
            raise MemoryError()

        body = {"origins": o.tolist(), "directions": v.tolist(),
                "values": np.ones((300, 1)).tolist()}
        monkeypatch.setattr(Field, "prepare", no_memory)
        r = tc.post("/v1/fields/f/samples", headers={"Idempotency-Key": "m"}, json=body)
        assert r.status_code == 503, r.text
        assert "out of memory" in r.text and "not stored" in r.text
        assert r.headers["retry-after"] == "1"
        assert c.describe("f")["storage"]["batches"] == 0
        monkeypatch.setattr(Field, "prepare", real_prepare)
        r = tc.post("/v1/fields/f/samples", headers={"Idempotency-Key": "m"}, json=body)
        assert r.status_code == 200 and not r.json()["replayed"], r.text
        monkeypatch.setattr(Field, "query", no_memory)
        r = tc.post("/v1/fields/f/query", json={"origins": o[:200].tolist(),
                                                 "directions": v[:200].tolist()})
        assert r.status_code == 503 and "out of memory" in r.text, r.text
        monkeypatch.setattr(Field, "query", real_query)
        assert c.query_rays("f", o[:200], v[:200]).inside.mean() > 0.5
    finally:
        tc.__exit__(None, None, None)


def test_non_ascii_api_keys_work(make_app):
    tc, _ = started(make_app(api_key="clé-secrète", read_only_key="lecture"))
    try:
        assert tc.get("/v1/fields", headers={"api-key": "clé-secrète".encode()}).status_code == 200
        assert tc.get("/v1/fields", headers={"api-key": "cle-secrete"}).status_code == 401
    finally:
        tc.__exit__(None, None, None)


def test_a_create_the_follower_applies_first_keeps_nothing_behind(make_app, monkeypatch):
    """The follower may apply a create's log entry before the request that committed
    it hands its field over: the field the request built must not stay behind (one
    empty field held for ever per create)."""
    tc, c = started(make_app())
    try:
        reg = tc.app.state.rooms
        real = reg.storage.create_field

        def create_field(*a, **kw):  # the follower wins the race
            fid, pos = real(*a, **kw)
            assert reg.follower.wait_applied(pos, 30)
            return fid, pos

        monkeypatch.setattr(reg.storage, "create_field", create_field)
        for i in range(3):
            c.create_field(f"g{i}", channels=1)
            c.delete_field(f"g{i}")
        assert reg.applier.built_count() == 0
    finally:
        tc.__exit__(None, None, None)
