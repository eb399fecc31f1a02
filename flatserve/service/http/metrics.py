"""Prometheus metrics (one registry per app) and the ASGI middleware timing requests.

Under ``serve --processes N`` every replica is a process of its own and a scrape
reaches one of them: the supervisor gives its children one directory for the
Prometheus client's multiprocess mode (``PROMETHEUS_MULTIPROC_DIR``), so the
counters and histograms of every replica (those of replicas that died and were
restarted too) are summed in whatever replica answers the scrape. Counters of work
every replica does itself for every batch (``flatserve_samples_accepted``,
``flatserve_log_apply_seconds``) carry a ``replica`` label, so they are not summed
into N times the samples; so do the gauges read at scrape time (fields, samples, log
position: the view of the replica that answered) and the process gauges
(``flatserve_replica_resident_bytes``, ``flatserve_replica_cpu_seconds``, each live
replica's own, refreshed every few seconds). One process alone also exports the
client's standard ``process_*`` series. No ``_created`` series.
"""
from __future__ import annotations

import os
import resource
import threading
import time

from prometheus_client import (CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector,
                               disable_created_metrics, generate_latest)
from prometheus_client.core import GaugeMetricFamily

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
#: The Prometheus client's multiprocess directory (set by the supervisor for its children)
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
#: Seconds between two refreshes of a replica's process gauges (multiprocess mode)
PROCESS_REFRESH_S = 5.0

# a `_created` series per counter is noise to an operator (and Prometheus ignores it)
disable_created_metrics()


def multiprocess_dir() -> str | None:
    """The multiprocess directory of this process, or None (one process alone)."""
    return os.environ.get(MULTIPROC_ENV) or None


def _resident_bytes() -> float:
    try:
        with open("/proc/self/statm") as f:
            return float(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def _cpu_seconds() -> float:
    u = resource.getrusage(resource.RUSAGE_SELF)
    return u.ru_utime + u.ru_stime


class Metrics:
    """The service's metrics.

    Parameters
    ----------
    replica : int
        This replica's index (``serve --processes N`` numbers its children), the
        ``replica`` label of the per-replica series.
    """

    def __init__(self, replica: int = 0) -> None:
        self.replica = str(replica)
        self.multiprocess = multiprocess_dir() is not None
        self.registry = CollectorRegistry()
        self._collectors: list = []
        # multiprocess mode: values live in the directory's files and are collected
        # from there at scrape time, never from this process's registry
        r = None if self.multiprocess else self.registry
        self.requests = Counter("flatserve_requests", "HTTP requests", ["method", "route", "status"],
                                registry=r)
        self.latency = Histogram(
            "flatserve_request_seconds", "HTTP request latency", ["method", "route"], registry=r,
            buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
        )
        self.samples_accepted = Counter(
            "flatserve_samples_accepted", "Samples triangulated by this replica (every replica "
            "triangulates every batch, replayed from the log at its start or not)", ["field", "replica"], registry=r)
        self.samples_rejected = Counter("flatserve_samples_rejected",
                                        "Samples rejected (outside the chart)", ["field"], registry=r)
        self.batches = Counter("flatserve_batches", "Upload batches stored", ["field"], registry=r)
        self.query_rows = Counter("flatserve_query_rows", "Flats queried", ["field"], registry=r)
        self.queries = Counter("flatserve_queries", "Query requests", ["field"], registry=r)
        self._apply = Histogram(
            "flatserve_log_apply_seconds", "Seconds this replica took to apply one batch of "
            "the log (chart unless charted here, then insert)", ["replica"], registry=r,
            buckets=(0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60))
        self.apply_seconds = self._apply.labels(self.replica)
        self.snapshots = Counter("flatserve_snapshots", "Snapshots written", ["field"], registry=r)
        self._resident = Gauge("flatserve_replica_resident_bytes", "Resident memory of a replica "
                               "process", ["replica"], registry=r,
                               multiprocess_mode="liveall").labels(self.replica)
        self._cpu = Gauge("flatserve_replica_cpu_seconds", "CPU seconds (user + system) of a "
                          "replica process", ["replica"], registry=r,
                          multiprocess_mode="liveall").labels(self.replica)
        self._refresh_process()
        if self.multiprocess:
            threading.Thread(target=self._refresh_loop, name="flatserve-metrics",
                             daemon=True).start()
        else:
            ProcessCollector(registry=self.registry)

    def accepted(self, field: str, n: int) -> None:
        """Count ``n`` samples this replica triangulated into ``field``."""
        self.samples_accepted.labels(field, self.replica).inc(n)

    def _refresh_process(self) -> None:
        self._resident.set(_resident_bytes())
        self._cpu.set(_cpu_seconds())

    def _refresh_loop(self) -> None:  # pragma: no cover - a daemon of replica processes
        while True:
            time.sleep(PROCESS_REFRESH_S)
            self._refresh_process()

    def watch(self, registry_obj) -> None:
        """Expose per-field gauges read from the field registry at scrape time."""
        replica = self.replica

        class _Fields:
            def collect(self_inner):
                g = GaugeMetricFamily("flatserve_field_samples", "Samples in a field (as the "
                                      "replica that answered sees it)", labels=["field", "replica"])
                n = GaugeMetricFamily("flatserve_fields", "Fields on this replica",
                                      labels=["replica"])
                entries = registry_obj.snapshot_entries()
                n.add_metric([replica], len(entries))
                for e in entries:
                    if e.field is not None:
                        g.add_metric([e.name, replica], e.field.nsamples)
                yield n
                yield g
                lag = getattr(registry_obj, "lag", None)
                info = lag() if lag is not None else None
                if info is not None:
                    for key, doc in (("position", "Log position this replica has applied"),
                                     ("head", "Position of the log's last committed entry"),
                                     ("lag_entries", "Log entries committed, not applied here"),
                                     ("lag_seconds", "Seconds since the oldest entry not "
                                                     "applied here was committed")):
                        m = GaugeMetricFamily(f"flatserve_log_{key}", doc, labels=["replica"])
                        m.add_metric([replica], float(info[key]))
                        yield m

        collector = _Fields()
        self._collectors.append(collector)
        self.registry.register(collector)

    def render(self) -> bytes:
        self._refresh_process()
        if not self.multiprocess:
            return generate_latest(self.registry)
        from prometheus_client import multiprocess

        reg = CollectorRegistry()
        multiprocess.MultiProcessCollector(reg)
        for c in self._collectors:
            reg.register(c)
        return generate_latest(reg)


class MetricsMiddleware:
    """Pure ASGI middleware: counts and times every HTTP request by route template."""

    def __init__(self, app, metrics: Metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = [500]

        async def _send(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
            await send(msg)

        try:
            await self.app(scope, receive, _send)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            self.metrics.requests.labels(scope["method"], path, str(status[0])).inc()
            self.metrics.latency.labels(scope["method"], path).observe(time.perf_counter() - t0)
