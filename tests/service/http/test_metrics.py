"""Metrics that are true under ``serve --processes N``: whichever replica answers a
scrape, the counters are those of all replicas summed (restarted ones included), each
replica's own work and process carry its ``replica`` label, and there is no
``_created`` noise."""
from __future__ import annotations

import time

import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

from flatserve.client import Client
from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.process import ServerProcess, children, kill9_and_await_restart


def _samples(text: str) -> dict[tuple, float]:
    """``{(name, ((label, value), ...)): value}`` of a scrape."""
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def _scrape(url: str) -> tuple[dict, str]:
    r = httpx.get(url + "/metrics", timeout=30)  # a new connection: either replica answers
    assert r.status_code == 200
    return _samples(r.text), r.text


def _value(samples: dict, name: str, **labels) -> float | None:
    return samples.get((name, tuple(sorted(labels.items()))))


def test_counters_summed_over_replicas_equal_the_requests_sent(tmp_path):
    rng = np.random.default_rng(11)
    uploads, queries, rows = 6, 8, 300
    with ServerProcess(tmp_path / "data", tmp_path / "s.log", processes=2,
                       snapshot_every=0) as srv:
        srv.wait_ready()
        kids = children(srv.proc.pid)
        assert len(kids) == 2
        with Client(srv.url) as c:
            c.create_field("small", basis=ONE_CHART)
        last, accepted = 0, 0
        for _ in range(uploads):
            with Client(srv.url) as c:  # a new connection each time
                o, v = paper_rays(rng, rows)
                up = c.upload_rays("small", o, v, rng.uniform(size=rows))
                last, accepted = up["position"], accepted + up["accepted"]
        for _ in range(queries):
            with Client(srv.url) as c:
                c.query_rays("small", *paper_rays(rng, 10), min_position=last)
        # both replicas have applied every batch: a describe waits on whichever replica
        # answers it, and the kernel may hand every new connection to the same one, so
        # wait until each replica's own count is the sum the uploads acknowledged
        deadline = time.monotonic() + 120
        while True:
            with Client(srv.url) as c:
                c.describe("small", min_position=last)
            s, _ = _scrape(srv.url)
            acc = [_value(s, "flatserve_samples_accepted_total", field="small", replica=r)
                   for r in ("0", "1")]
            if acc == [accepted, accepted] or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        answered = set()
        for _ in range(10):
            s, text = _scrape(srv.url)
            assert "_created" not in text
            assert _value(s, "flatserve_batches_total", field="small") == uploads
            assert _value(s, "flatserve_queries_total", field="small") == queries
            assert _value(s, "flatserve_query_rows_total", field="small") == 10 * queries
            assert _value(s, "flatserve_requests_total", method="POST",
                          route="/v1/fields/{name}/samples", status="200") == uploads
            # each replica's own work, under its label: both triangulated every batch
            acc = [_value(s, "flatserve_samples_accepted_total", field="small", replica=r)
                   for r in ("0", "1")]
            assert acc == [accepted, accepted] and accepted > 0.9 * uploads * rows
            # each live replica's process, under its label (and pid)
            procs = {dict(lbl)["pid"] for (name, lbl) in s
                     if name == "flatserve_replica_resident_bytes"}
            assert procs == {str(k) for k in kids}
            answered |= {dict(lbl)["replica"] for (name, lbl) in s if name == "flatserve_fields"}
        # a replica killed and restarted: its counts stay in the sums, its process goes
        kill9_and_await_restart(srv.proc.pid, kids[0], 2)
        with Client(srv.url) as c:
            c.wait_ready(60)
        # the new process replayed every batch from the log (no snapshots): it
        # triangulated them all again, under the label of the one it replaces
        deadline = time.monotonic() + 120
        while True:
            s, _ = _scrape(srv.url)
            acc = sorted(_value(s, "flatserve_samples_accepted_total", field="small",
                                replica=r) for r in ("0", "1"))
            if acc == [accepted, 2 * accepted] or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert acc == [accepted, 2 * accepted]
        for _ in range(6):
            s, _ = _scrape(srv.url)
            assert _value(s, "flatserve_batches_total", field="small") == uploads
            assert _value(s, "flatserve_queries_total", field="small") == queries
            procs = {dict(lbl)["pid"] for (name, lbl) in s
                     if name == "flatserve_replica_resident_bytes"}
            assert str(kids[0]) not in procs
    assert answered <= {"0", "1"}
