"""Cluster mode through a sequence of faults, as one deployment lives them: a node
lost, a raylet killed with ``kill -9``, a front killed with ``kill -9``, then the
whole cluster (every node and front) gone and started again on the same log
(PostgreSQL), while a writer uploads and a reader queries through the fronts.

Every acknowledged batch must be stored under its key at the batch number it was
acknowledged with; no query may get a 200 with a partial answer or any status but
503 (a field whose copies are being placed again) during the faults; and at the
end the field must answer bit for bit as a lone server (no Ray, its own SQLite
data directory) fed the same batches, in the same order. Bounded: a few seconds
a fault, a few minutes in all.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

import httpx
import numpy as np

from flatserve.client import Client, ServiceError
from tests.harness.cluster import Fronts, sphere_rays
from tests.harness.process import ServerProcess
from tests.harness.raycluster import RayNodes

#: seconds each fault is left to play before the next
SETTLE_S = 6.0
#: rows of each batch the writer uploads
ROWS = 300
#: statuses a client may get while a fault plays (the request is retried)
TRANSIENT = (429, 503)


class Traffic:
    """A writer and a reader on the field ``name`` through the live fronts (the
    ``urls`` list, changed by the test as fronts die and start), until :meth:`stop`.

    The writer uploads batch ``i`` under the key ``w<i>`` (``wait=false``: an upload
    never waits for the shards), retrying the same batch under the same key until
    it is acknowledged; ``sent`` keeps every batch sent, ``acked`` the batch number
    each key was acknowledged with. The reader queries the first rays of ``probe``:
    an answer is whole (most rays inside) or a 503.
    """

    def __init__(self, name: str, urls: list[str], probe, seed: int) -> None:
        self.name, self.urls, self.probe = name, urls, probe
        self.rng = np.random.default_rng(seed)
        self.sent: dict[str, tuple] = {}
        self.acked: dict[str, int] = {}
        self.failures: list = []
        self.answered = self.refused = 0
        self.i = 0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        self._stop.clear()
        self._threads = [threading.Thread(target=self._write, daemon=True),
                         threading.Thread(target=self._read, daemon=True)]
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(180)
            assert not t.is_alive(), "traffic did not stop"

    def _url(self, n: int) -> str:
        urls = list(self.urls)
        return urls[n % len(urls)]

    def _write(self) -> None:
        tries = 0
        while not self._stop.is_set():
            key = f"w{self.i}"
            if key not in self.sent:
                o, d = sphere_rays(self.rng, ROWS)
                self.sent[key] = (o, d, self.rng.uniform(size=(ROWS, 2)))
            o, d, v = self.sent[key]
            try:
                with Client(self._url(tries), retries=0, timeout=60) as c:
                    self.acked[key] = c.upload_rays(self.name, o, d, v, idempotency_key=key,
                                                    wait=False)["batch"]
                self.i += 1
            except httpx.TransportError:  # its front died: the same batch elsewhere
                tries += 1
            except ServiceError as exc:
                if exc.status not in TRANSIENT:
                    self.failures.append(("upload", key, repr(exc)))
                tries += 1
            time.sleep(0.05)

    def _read(self) -> None:
        o, d = self.probe[0][:40], self.probe[1][:40]
        n = 0
        while not self._stop.is_set():
            n += 1
            try:
                with Client(self._url(n), retries=0, timeout=60) as c:
                    got = c.query_rays(self.name, o, d)
                if got.inside.mean() <= 0.5:
                    self.failures.append(("query", "a partial answer presented as whole"))
                self.answered += 1
            except httpx.TransportError:
                pass
            except ServiceError as exc:
                if exc.status not in TRANSIENT:
                    self.failures.append(("query", repr(exc)))
                self.refused += 1
            time.sleep(0.1)


def raylet_pid(node) -> int:
    """The process id of a Ray node's raylet."""
    (info,) = node.all_processes["raylet"]
    return info.process.pid


def answer(url: str, name: str, probe, position: int, timeout: float = 240.0):
    """The field's answer to ``probe`` once it has applied the log up to ``position``
    (503 while its shards restore: asked again)."""
    end = time.monotonic() + timeout
    with Client(url, retries=0, timeout=120) as c:
        while True:
            try:
                return c.query_rays(name, *probe, min_position=position)
            except ServiceError as exc:
                assert exc.status == 503 and time.monotonic() < end, exc
                time.sleep(1.0)


def test_node_raylet_front_and_whole_cluster_faults_lose_nothing(tmp_path, pg_url, rng):
    probe = sphere_rays(rng, 1500)
    urls: list[str] = []
    traffic = Traffic("f", urls, probe, seed=41)
    opts = {"ray_shards": 2, "read_wait_timeout": 30}
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=2))
        fronts = Fronts(tmp_path, pg_url, nodes.address, stack, **opts)
        a, b = fronts.start(), fronts.start()
        urls += [a.url, b.url]
        with Client(a.url, retries=0, timeout=120) as c:
            c.create_field("f", channels=2, copies=2)
            o, d = sphere_rays(rng, 3000)  # (not the writer's: fed to the lone server first)
            traffic.sent["w-first"] = (o, d, rng.uniform(size=(3000, 2)))
            traffic.acked["w-first"] = c.upload_rays("f", *traffic.sent["w-first"],
                                                     idempotency_key="w-first")["batch"]
        traffic.start()
        time.sleep(SETTLE_S)
        # a node with shards on it is lost (its raylet and its workers), then replaced
        nodes.kill(nodes.workers[0])
        time.sleep(SETTLE_S)
        nodes.add_worker()
        time.sleep(SETTLE_S)
        # a raylet killed with kill -9 (its workers left to notice), then replaced
        victim = nodes.workers[0]
        os.kill(raylet_pid(victim), signal.SIGKILL)
        time.sleep(SETTLE_S)
        nodes.kill(victim)  # (its processes reaped)
        nodes.add_worker()
        time.sleep(SETTLE_S)
        # a front killed with kill -9 in the middle of requests; the other serves on
        a.kill9()
        urls.remove(a.url)
        time.sleep(SETTLE_S)
        # the whole cluster gone: every front, every node
        traffic.stop()
        b.kill9()
        nodes.shutdown()
    assert not traffic.failures, traffic.failures[:5]
    assert traffic.answered > 0 and len(traffic.acked) > 10, (traffic.answered, traffic.acked)
    (tmp_path / "again").mkdir()
    with contextlib.ExitStack() as stack:  # a new cluster, a new front, on the same log
        nodes = stack.enter_context(RayNodes(workers=2))
        c_front = Fronts(tmp_path / "again", pg_url, nodes.address, stack, **opts).start()
        urls[:] = [c_front.url]
        traffic.start()
        time.sleep(SETTLE_S)
        traffic.stop()
        assert not traffic.failures, traffic.failures[:5]
        with Client(c_front.url, retries=0, timeout=120) as c:
            stored = c.batches("f")
            head = c.describe("f")["position"]
        keys = {x["idempotency_key"]: x["batch"] for x in stored}
        lost = {k: v for k, v in traffic.acked.items() if keys.get(k) != v}
        assert not lost, f"acknowledged batches not stored as acknowledged: {lost}"
        assert set(keys) <= set(traffic.sent), set(keys) - set(traffic.sent)
        got = answer(c_front.url, "f", probe, head)
        # a lone server fed the stored batches in their order
        lone = stack.enter_context(ServerProcess(tmp_path / "lone", tmp_path / "lone.log",
                                                 snapshot_every=0))
        lone.wait_ready(120)
        with Client(lone.url, retries=0, timeout=120) as c:
            c.create_field("f", channels=2, copies=2)
            for x in sorted(stored, key=lambda x: x["batch"]):
                c.upload_rays("f", *traffic.sent[x["idempotency_key"]],
                              idempotency_key=x["idempotency_key"])
            want = c.query_rays("f", *probe)
            nsamples = c.describe("f")["nsamples"]
        with Client(c_front.url, retries=0, timeout=120) as c:
            end = time.monotonic() + 60
            while c.describe("f")["nsamples"] != nsamples and time.monotonic() < end:
                time.sleep(0.5)  # (the shards report their sizes each second)
            assert c.describe("f")["nsamples"] == nsamples
    assert want.inside.sum() > 1000
    np.testing.assert_array_equal(got.inside, want.inside)
    np.testing.assert_array_equal(got.values, want.values)  # bit for bit
