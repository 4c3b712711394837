"""Prometheus metrics of one app (its own registry, so several apps in one process never share counters).
GET /metrics exposes them in the text format."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

# seconds; renders are ~0.05-0.5 s, reconstructions ~0.5-5 s on 2 cores (docs/api.md)
_LATENCY = (0.005, 0.01, 0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.5, 5.0, 10.0, 30.0, 60.0)


class _StoreCollector:
    def __init__(self, store):
        self.store = store

    def collect(self):
        u = self.store.usage()
        scenes = GaugeMetricFamily("xyzcyl_scenes", "scenes in the store by state", labels=["state"])
        for state, n in u["scenes"].items():
            scenes.add_metric([state], n)
        yield scenes
        yield GaugeMetricFamily("xyzcyl_store_bytes", "bytes of ready scenes in the store", value=u["bytes"])
        # a counter (exposed as xyzcyl_store_evictions_total): it only grows, so rate() and increase() apply
        yield CounterMetricFamily("xyzcyl_store_evictions", "scenes evicted by the quota since start",
                                  value=u["evicted"])


class Metrics:
    def __init__(self):
        r = self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter("xyzcyl_http_requests", "HTTP requests by route template, method and status",
                                ["route", "method", "status"], registry=r)
        self.latency = Histogram("xyzcyl_http_request_duration_seconds", "time to the response's first byte",
                                 ["route", "method"], buckets=_LATENCY, registry=r)
        self.reconstruct_seconds = Histogram("xyzcyl_reconstruction_duration_seconds",
                                             "worker time of a successful reconstruction", buckets=_LATENCY,
                                             registry=r)
        self.reconstructions = Counter("xyzcyl_reconstructions", "finished reconstructions by outcome",
                                       ["outcome"], registry=r)
        self.render_seconds = Histogram("xyzcyl_render_duration_seconds", "render + encode time of one view",
                                        buckets=_LATENCY, registry=r)
        self.queue_depth = Gauge("xyzcyl_queue_depth", "work running or waiting", ["queue"], registry=r)
        self.rejected = Counter("xyzcyl_rejected", "requests refused because a queue was full", ["queue"],
                                registry=r)
        self.grpc_requests = Counter("xyzcyl_grpc_requests", "SensorsimService gRPC calls by method and status code",
                                     ["method", "code"], registry=r)
        self.grpc_latency = Histogram("xyzcyl_grpc_request_duration_seconds", "time to a gRPC call's answer",
                                      ["method"], buckets=_LATENCY, registry=r)
        self.render_cache = Counter("xyzcyl_render_cache", "render cache lookups", ["result"], registry=r)
        for q in ("reconstruct", "render"):
            self.queue_depth.labels(q).set(0)

    def watch_store(self, store) -> None:
        self.registry.register(_StoreCollector(store))

    def exposition(self) -> bytes:
        return generate_latest(self.registry)


__all__ = ["Metrics"]
