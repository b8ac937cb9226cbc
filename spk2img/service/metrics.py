"""Prometheus metrics of one app (its own registry, so several apps can live in one process)."""

from __future__ import annotations

import time
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300)


class ServiceMetrics:
    """Requests, latency, frames in and out, errors, queue depth and admitted requests."""

    def __init__(self):
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "spk2img_http_requests",
            "HTTP requests answered",
            ("method", "path", "status"),
            registry=self.registry,
        )
        self.latency = Histogram(
            "spk2img_http_request_duration_seconds",
            "Wall time of a request, upload included",
            ("method", "path"),
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.spike_frames = Counter(
            "spk2img_spike_frames_received",
            "Spike frames decoded from uploads",
            ("method",),
            registry=self.registry,
        )
        self.frames = Counter(
            "spk2img_frames_sent",
            "Reconstructed frames sent",
            ("method", "format"),
            registry=self.registry,
        )
        self.errors = Counter(
            "spk2img_errors",
            "Errors: http (an error response), in_band (an ERRO record), "
            "disconnect (the client left mid-request)",
            ("status", "kind"),
            registry=self.registry,
        )
        self.queue_depth = Gauge(
            "spk2img_inference_queue_depth",
            "Reconstruction jobs submitted and not finished",
            registry=self.registry,
        )
        self.admitted = Gauge(
            "spk2img_admitted_requests",
            "Reconstruction requests holding an admission",
            registry=self.registry,
        )

    def watch_pool(self, jobs: Callable[[], int], admitted: Callable[[], int]) -> None:
        """Read the queue depth and admissions from the pool at each scrape."""
        self.queue_depth.set_function(jobs)
        self.admitted.set_function(admitted)

    def exposition(self) -> bytes:
        """The Prometheus text format of every metric."""
        return generate_latest(self.registry)


class MetricsMiddleware:
    """Pure ASGI middleware (it leaves ``receive`` alone, so full-duplex routes keep working):
    counts each HTTP request by route template and status, and times it to its last byte."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = "disconnect"

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = str(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", "unmatched")
            method = scope["method"]
            self.metrics.requests.labels(method, path, status).inc()
            self.metrics.latency.labels(method, path).observe(time.perf_counter() - start)
            if status.isdigit() and int(status) >= 400:
                self.metrics.errors.labels(status, "http").inc()
