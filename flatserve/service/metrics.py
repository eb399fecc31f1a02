"""Prometheus metrics (one registry per app) and the ASGI middleware timing requests."""
from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("flatserve_requests", "HTTP requests", ["method", "route", "status"],
                                registry=r)
        self.latency = Histogram(
            "flatserve_request_seconds", "HTTP request latency", ["method", "route"], registry=r,
            buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
        )
        self.samples_accepted = Counter("flatserve_samples_accepted", "Samples triangulated",
                                        ["field"], registry=r)
        self.samples_rejected = Counter("flatserve_samples_rejected",
                                        "Samples rejected (outside the chart)", ["field"], registry=r)
        self.batches = Counter("flatserve_batches", "Upload batches stored", ["field"], registry=r)
        self.query_rows = Counter("flatserve_query_rows", "Flats queried", ["field"], registry=r)
        self.queries = Counter("flatserve_queries", "Query requests", ["field"], registry=r)
        self.apply_seconds = Histogram(
            "flatserve_log_apply_seconds", "Seconds this replica took to apply one batch of "
            "the log (chart unless charted here, then insert)", registry=r,
            buckets=(0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60))
        self.snapshots = Counter("flatserve_snapshots", "Snapshots written", ["field"], registry=r)

    def watch(self, registry_obj) -> None:
        """Expose per-field gauges read from the field registry at scrape time."""

        class _Fields:
            def collect(self_inner):
                g = GaugeMetricFamily("flatserve_field_samples", "Samples in a field", labels=["field"])
                n = GaugeMetricFamily("flatserve_fields", "Fields on this server")
                entries = registry_obj.snapshot_entries()
                n.add_metric([], len(entries))
                for e in entries:
                    if e.field is not None:
                        g.add_metric([e.name], e.field.nsamples)
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
                        m = GaugeMetricFamily(f"flatserve_log_{key}", doc)
                        m.add_metric([], float(info[key]))
                        yield m

        self.registry.register(_Fields())

    def render(self) -> bytes:
        return generate_latest(self.registry)


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
