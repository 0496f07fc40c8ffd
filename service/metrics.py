"""Prometheus metrics of one app instance.

Each app gets its own :class:`~prometheus_client.CollectorRegistry` (not the process-global default) so tests
can build many apps in one process and so two apps never mix counts. Label values are bounded: routes are the
route templates (unknown paths collapse into ``other``), reasons are the error codes of ``service.errors``.
"""

from __future__ import annotations

from typing import Any

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

# Seconds: from a cached health check to a large L1 reconstruction.
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)


class ServiceMetrics:
    """Requests by route/status, latency, in-flight, rejections by reason, inference queue and durations."""

    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter("gradsep_http_requests", "HTTP requests answered, by route, method and status",
                                ["route", "method", "status"], registry=r)
        self.latency = Histogram("gradsep_http_request_duration_seconds",
                                 "time from request start to the last response byte, by route",
                                 ["route"], buckets=LATENCY_BUCKETS, registry=r)
        self.in_flight = Gauge("gradsep_http_requests_in_flight", "HTTP requests being handled now", registry=r)
        self.rejections = Counter("gradsep_rejections", "requests answered with an error, by error code",
                                  ["reason"], registry=r)
        self.inference = Histogram("gradsep_inference_duration_seconds",
                                   "decode + reconstruction + encode time of successful requests, by method",
                                   ["method"], buckets=LATENCY_BUCKETS, registry=r)
        self.queue_waiting = Gauge("gradsep_inference_queue_waiting", "requests waiting for an inference slot",
                                   registry=r)
        self.inference_running = Gauge("gradsep_inference_running",
                                       "inference threads running (timed-out ones included until they end)",
                                       registry=r)
        self.ready = Gauge("gradsep_ready", "1 once models are loaded and warmed up", registry=r)
        self.body_memory = Gauge("gradsep_request_body_memory_bytes",
                                 "request-body bytes held in memory, across all open uploads (at most "
                                 "GRADSEP_BODY_MEMORY_BYTES)", registry=r)

    def bind_engine(self, engine: Any) -> None:
        """Read queue and readiness gauges from the engine at scrape time instead of mirroring every change."""
        self.queue_waiting.set_function(lambda: engine.gate.waiting if engine.gate is not None else 0)
        self.inference_running.set_function(lambda: engine.gate.running if engine.gate is not None else 0)
        self.ready.set_function(lambda: 1.0 if engine.state == "ready" else 0.0)
        self.body_memory.set_function(lambda: engine.body_pool.held)

    def render(self) -> bytes:
        return generate_latest(self.registry)
