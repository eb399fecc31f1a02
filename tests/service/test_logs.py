"""Logs an operator can use: an access line per request (refusals too), one format for
flatserve's and uvicorn's lines, JSON lines on request, log lines that do not break a
progress bar, the access log switchable from the command line."""
from __future__ import annotations

import argparse
import io
import json
import logging
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.service import logs
from flatserve.service.server import add_arguments, settings_from_args
from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.process import ServerProcess

NPY = "application/x-npy"


def _npy(a) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(a, np.float64))
    return buf.getvalue()


@pytest.fixture
def restore_logging():
    """Put the root logger back as it was (``logs.configure`` replaces its handlers)."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for h in list(root.handlers):
        root.removeHandler(h)
    for h in handlers:
        root.addHandler(h)
    root.setLevel(level)
    logging.getLogger("uvicorn.access").disabled = False


def _access(caplog) -> list[dict]:
    return [{k: getattr(r, k, None) for k in ("method", "route", "field", "rows", "status",
                                              "ms", "request_id")}
            for r in caplog.records if r.name == logs.ACCESS_LOGGER]


def test_every_request_gets_an_access_line_refusals_too(make_app, rng, caplog):
    caplog.set_level(logging.INFO, logger=logs.ACCESS_LOGGER)
    o, v = paper_rays(rng, 50)
    with TestClient(make_app(max_batch_rows=40), base_url="http://127.0.0.1") as tc:
        tc.post("/v1/fields", json={"name": "f", "basis": ONE_CHART})
        tc.post("/v1/fields", json={"name": "f"})                                    # 409
        r = tc.post("/v1/fields/f/samples", content=_npy(np.c_[o[:30], v[:30], np.ones(30)]),
                    headers={"Content-Type": NPY, "X-Request-ID": "upload-1"})
        assert r.status_code == 200 and r.headers["x-request-id"] == "upload-1"
        tc.post("/v1/fields/f/samples", content=_npy(np.c_[o, v, np.ones(50)]),
                headers={"Content-Type": NPY})                                       # 413
        tc.post("/v1/fields/f/samples", content=b"", headers={"Content-Type": NPY})  # 422
        q = tc.post("/v1/fields/f/query", content=_npy(np.c_[o[:7], v[:7]]),        # fast path
                    headers={"Content-Type": NPY, "X-Request-ID": "bad id with spaces"})
        assert q.status_code == 200 and q.headers["x-request-id"] != "bad id with spaces"
    lines = _access(caplog)
    got = [(a["method"], a["route"], a["field"], a["rows"], a["status"]) for a in lines
           if a["route"] != "/readyz"]
    assert got == [
        ("POST", "/v1/fields", "f", None, 201),  # the field named in the body
        ("POST", "/v1/fields", "f", None, 409),
        ("POST", "/v1/fields/{name}/samples", "f", 30, 200),
        ("POST", "/v1/fields/{name}/samples", "f", None, 413),  # refused from the header
        ("POST", "/v1/fields/{name}/samples", "f", None, 422),
        ("POST", "/v1/fields/{name}/query", "f", 7, 200),
    ]
    ids = [a["request_id"] for a in lines]
    assert "upload-1" in ids and len(set(ids)) == len(ids)
    assert all(a["ms"] >= 0 for a in lines)
    text = [r.getMessage() for r in caplog.records if r.name == logs.ACCESS_LOGGER]
    assert "POST /v1/fields/{name}/samples 200" in text[2] and "rows=30" in text[2]
    assert "request_id=upload-1" in text[2]


def test_access_log_off(make_app, caplog):
    caplog.set_level(logging.INFO, logger=logs.ACCESS_LOGGER)
    with TestClient(make_app(access_log=False), base_url="http://127.0.0.1") as tc:
        assert tc.get("/healthz").status_code == 200
        assert "x-request-id" not in tc.get("/healthz").headers
    assert not _access(caplog)
    p = argparse.ArgumentParser()
    add_arguments(p)
    assert settings_from_args(p.parse_args(["--no-access-log"])).access_log is False
    assert settings_from_args(p.parse_args([])).access_log is True
    assert settings_from_args(p.parse_args(["--log-format", "json"])).log_format == "json"


def test_json_lines_hold_the_access_fields(restore_logging):
    out = io.StringIO()
    logs.configure("info", "json", stream=out)
    logging.getLogger(logs.ACCESS_LOGGER).info("GET /x 200", extra={"route": "/x", "status": 200})
    try:
        raise ValueError("boom")
    except ValueError:
        logging.getLogger("flatserve.service").exception("it failed")
    logging.getLogger("uvicorn.error").info("Started server process")
    docs = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [d["logger"] for d in docs] == [logs.ACCESS_LOGGER, "flatserve.service",
                                          "uvicorn.error"]
    assert docs[0]["route"] == "/x" and docs[0]["status"] == 200 and docs[0]["pid"] > 0
    assert "ValueError: boom" in docs[1]["exception"] and docs[1]["level"] == "ERROR"
    with pytest.raises(ValueError, match="log_format"):
        logs.configure("info", "xml")


def test_a_log_line_goes_above_a_progress_bar(restore_logging):
    from tqdm import tqdm

    out = io.StringIO()
    logs.configure("info", "text", stream=out)
    with tqdm(total=10, desc="building demo", file=out, mininterval=0) as bar:
        bar.update(3)
        logging.getLogger("flatserve.service").info("snapshot of 'bunny' written")
        bar.update(3)
    # what a terminal shows of each line: the text after its last carriage return
    shown = [line.rsplit("\r", 1)[-1] for line in out.getvalue().split("\n")]
    msg = [s for s in shown if "snapshot of 'bunny' written" in s]
    assert len(msg) == 1 and "building demo" not in msg[0], shown
    assert msg[0].index("INFO flatserve.service[") > 0


def test_a_real_server_logs_json_only(tmp_path, rng):
    log = tmp_path / "server.log"
    with ServerProcess(tmp_path / "data", log, log_format="json") as srv:
        srv.wait_ready()
        from flatserve.client import Client

        with Client(srv.url) as c:
            c.create_field("f", basis=ONE_CHART)
            o, v = paper_rays(rng, 20)
            c.upload_rays("f", o, v, np.ones(20))
            with pytest.raises(Exception):
                c.create_field("f")
        time.sleep(0.2)
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    docs = [json.loads(ln) for ln in lines]  # every line, uvicorn's too, is a JSON object
    assert any(d["logger"].startswith("uvicorn") for d in docs)
    access = [d for d in docs if d["logger"] == logs.ACCESS_LOGGER]
    assert {(d["route"], d["status"]) for d in access} >= {
        ("/v1/fields", 201), ("/v1/fields", 409), ("/v1/fields/{name}/samples", 200)}
    assert [d["rows"] for d in access if d["route"].endswith("/samples")] == [20]
