"""Every answer is bounded before it is computed: a JSON answer by
``max_json_answer_bytes``, a binary one by ``max_answer_bytes``, with a 413
naming the estimate, the limit and the bulk path; large answers are encoded off
the event loop, so ``/healthz`` answers within a second whatever runs."""
from __future__ import annotations

import asyncio
import threading
import time

import httpx
import numpy as np

from flatserve import flats as flats_mod
from flatserve.service.http import codec
from tests.harness.fields import SINGLE, paper_rays
from tests.harness.process import ServerProcess
from tests.harness.service import running, started


def _never(*a, **kw):  # pragma: no cover - the point is that it is not called
    raise AssertionError("the work was started although its answer is refused")


def test_math_project_answer_is_refused_before_it_is_computed(make_app, monkeypatch):
    """k = 0, d = 8: each weight row answers 82 numbers; past the JSON limit the
    request is a 413 naming the estimate and the limit, and nothing is computed."""
    tc, _ = started(make_app(max_json_answer_bytes=1_000_000))
    try:
        Q = np.broadcast_to(np.eye(8), (2, 8, 8)).tolist()
        rows = 1_000_000 // (82 * codec.JSON_BYTES_PER_NUMBER) + 1
        body = {"k": 0, "d": 8, "flats": {"Q": Q, "r": np.zeros((2, 8)).tolist()},
                "weights": np.full((rows, 2), 0.5).tolist()}
        monkeypatch.setattr(flats_mod, "affine_combination", _never)
        r = tc.post("/v1/math/project", json=body)
        assert r.status_code == 413, r.text
        detail = r.json()["detail"]
        assert "FLATSERVE_MAX_JSON_ANSWER_BYTES" in detail and f"{rows:,} rows" in detail
        assert f"at most {rows - 1:,} rows" in detail and "in-process" in detail
        monkeypatch.undo()
        body["weights"] = body["weights"][:rows - 1]
        r = tc.post("/v1/math/project", json=body)
        assert r.status_code == 200, r.text
        assert len(r.content) <= 1_000_000
    finally:
        tc.__exit__(None, None, None)


def test_math_coordinates_answer_is_bounded(make_app, rng):
    with running(make_app(max_json_answer_bytes=200_000)) as (tc, _):
        o, v = paper_rays(rng, 2000)
        body = {"k": 1, "d": 3, "basis": {"kind": "tangent_simplex"}, "embed": True,
                "flats": {"origins": o.tolist(), "directions": v.tolist()}}
        r = tc.post("/v1/math/coordinates", json=body)
        assert r.status_code == 413 and "FLATSERVE_MAX_JSON_ANSWER_BYTES" in r.text, r.text
        fits = 200_000 // ((5 + 2 + 4) * codec.JSON_BYTES_PER_NUMBER)
        body["flats"] = {"origins": o[:fits].tolist(), "directions": v[:fits].tolist()}
        r = tc.post("/v1/math/coordinates", json=body)
        assert r.status_code == 200, r.text
        assert len(r.content) <= 200_000


def test_query_answers_are_bounded_per_format(make_app, rng):
    """A 64-channel query: as JSON past the JSON limit a 413 that points at .npy (which
    answers it); as .npy past the binary limit a 413 too. The field is not queried."""
    tc, c = started(make_app(max_json_answer_bytes=400_000, max_answer_bytes=2_000_000))
    try:
        c.create_field("f", channels=64, basis=SINGLE.basis)
        o, v = paper_rays(rng, 500)
        c.upload_rays("f", o, v, rng.uniform(size=(500, 64)))
        q = paper_rays(rng, 3000)
        arr = np.c_[q[0], q[1]]
        r = tc.post("/v1/fields/f/query", content=codec.npy_bytes(arr),
                    headers={"content-type": codec.NPY})  # JSON answer by default
        assert r.status_code == 413, r.text
        assert "application/x-npy" in r.json()["detail"], r.text
        r = tc.post("/v1/fields/f/query", content=codec.npy_bytes(arr),
                    headers={"content-type": codec.NPY, "accept": codec.NPY})
        assert r.status_code == 200 and len(r.content) <= 2_000_000
        big = np.tile(arr, (2, 1))  # 6000 rows x 65 columns x 8 bytes > 2 MB
        r = tc.post("/v1/fields/f/query", content=codec.npy_bytes(big),
                    headers={"content-type": codec.NPY, "accept": codec.NPY})
        assert r.status_code == 413 and "FLATSERVE_MAX_ANSWER_BYTES" in r.text, r.text
    finally:
        tc.__exit__(None, None, None)


def test_render_npy_frame_is_bounded(make_app, rng):
    tc, c = started(make_app(max_answer_bytes=100_000))
    try:
        c.create_field("f", channels=3)
        cam = {"width": 200, "height": 200, "supersample": 1}
        r = tc.post("/v1/fields/f/render", json={**cam, "format": "npy"})
        assert r.status_code == 413 and "FLATSERVE_MAX_ANSWER_BYTES" in r.text, r.text
        assert tc.post("/v1/fields/f/render", json=cam).status_code == 200  # PNG
    finally:
        tc.__exit__(None, None, None)


def test_large_answers_are_encoded_off_the_event_loop(make_app, rng, monkeypatch):
    """A query's answer is encoded where its query ran: inline for a handful of rows,
    in the thread pool for more, never holding the event loop for a large answer."""
    seen = []
    real = codec.query_response

    def spy(*a, **kw):
        try:
            asyncio.get_running_loop()
            seen.append("loop")
        except RuntimeError:
            seen.append("worker")
        return real(*a, **kw)

    monkeypatch.setattr(codec, "query_response", spy)
    tc, c = started(make_app())
    try:
        c.create_field("f", channels=1)
        o, v = paper_rays(rng, 300)
        c.upload_rays("f", o, v, rng.uniform(size=300))
        for n in (5, 5000):
            q = paper_rays(rng, n)
            r = tc.post("/v1/fields/f/query", json={"origins": q[0].tolist(),
                                                    "directions": q[1].tolist()})
            assert r.status_code == 200
        assert seen == ["loop", "worker"]
    finally:
        tc.__exit__(None, None, None)


def test_healthz_answers_within_a_second_during_worst_cases(tmp_path, rng):
    """A real server: while clients send the largest requests the limits admit (three
    .npy queries of max_batch_rows rows, a JSON query and a math projection each at
    the JSON answer limit) and ones past them, /healthz answers within 1 s."""
    rows = 100_000
    with ServerProcess(tmp_path / "data", tmp_path / "s.log", snapshot_every=0,
                       max_batch_rows=rows, max_json_answer_bytes=16 << 20,
                       max_json_bytes=16 << 20) as srv:
        srv.wait_ready()
        from flatserve.client import Client

        with Client(srv.url) as c:
            c.create_field("f", channels=8)
            o, v = paper_rays(rng, 20_000)
            c.upload_rays("f", o, v, rng.uniform(size=(20_000, 8)))
        q = paper_rays(rng, rows)
        npy = codec.npy_bytes(np.c_[q[0], q[1]])
        json_rows = (16 << 20) // (10 * codec.JSON_BYTES_PER_NUMBER)
        jq = {"origins": q[0][:json_rows].tolist(), "directions": q[1][:json_rows].tolist()}
        proj_rows = min(rows, (16 << 20) // (82 * codec.JSON_BYTES_PER_NUMBER))
        proj = {"k": 0, "d": 8, "flats": {"Q": np.broadcast_to(np.eye(8), (2, 8, 8)).tolist(),
                                          "r": np.zeros((2, 8)).tolist()},
                "weights": np.full((proj_rows, 2), 0.5).tolist()}
        over = {**proj, "weights": np.full((proj_rows * 3, 2), 0.5).tolist()}
        jobs = [("/v1/fields/f/query", dict(content=npy, headers={"content-type": codec.NPY,
                                                                  "accept": codec.NPY}))] * 3
        jobs += [("/v1/fields/f/query", dict(json=jq)), ("/v1/math/project", dict(json=proj)),
                 ("/v1/math/project", dict(json=over))]
        statuses = []

        def run(path, kw):
            with httpx.Client(base_url=srv.url, timeout=300) as h:
                for _ in range(2):
                    statuses.append((path, h.post(path, **kw).status_code))

        threads = [threading.Thread(target=run, args=job) for job in jobs]
        worst = 0.0
        with httpx.Client(base_url=srv.url, timeout=30) as h:
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                t0 = time.perf_counter()
                assert h.get("/healthz").status_code == 200
                worst = max(worst, time.perf_counter() - t0)
                time.sleep(0.05)
        for t in threads:
            t.join()
        assert sorted(set(statuses)) == sorted({("/v1/fields/f/query", 200),
                                                ("/v1/math/project", 200),
                                                ("/v1/math/project", 413)}), statuses
        assert worst < 1.0, f"/healthz took {worst:.2f} s"
