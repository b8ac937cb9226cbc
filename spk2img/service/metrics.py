"""Prometheus metrics of one app (its own registry, so several apps can live in one process)."""

from __future__ import annotations

import time
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300)

OTHER = "other"
"""The label value every value outside a label's known set folds into."""
HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")
STATUSES = tuple(map(str, (200, 400, 404, 405, 408, 413, 415, 422, 500, 503))) + ("disconnect",)
RECON_METHODS = ("net", "tfp", "tfi")
FORMATS = ("float32", "uint8", "png")
ERROR_KINDS = ("http", "in_band", "disconnect", "slow_upload", "unread")
REFUSALS = ("busy", "memory", "connections", "header_timeout")


class BoundedLabels:
    """A labelled metric whose every label takes one of a fixed set of values: any other value
    is counted as :data:`OTHER`, so no client can add series (random methods, paths, formats)."""

    def __init__(self, metric, *allowed: tuple[str, ...]):
        self.metric = metric
        self.allowed = tuple(frozenset(values) for values in allowed)

    def labels(self, *values: object):
        folded = (
            text if (text := str(value)) in allowed else OTHER
            for value, allowed in zip(values, self.allowed, strict=True)
        )
        return self.metric.labels(*folded)


class ServiceMetrics:
    """Requests, latency, frames in and out, errors, refusals, queue depth, admitted requests,
    reserved memory and open connections. Every label set is bounded (:class:`BoundedLabels`);
    ``paths`` are the route templates (set by the app), anything else is ``unmatched``."""

    def __init__(self):
        self.registry = CollectorRegistry()
        self.paths: frozenset[str] = frozenset()
        requests = Counter(
            "spk2img_http_requests",
            "HTTP requests answered",
            ("method", "path", "status"),
            registry=self.registry,
        )
        latency = Histogram(
            "spk2img_http_request_duration_seconds",
            "Wall time of a request, upload included",
            ("method", "path"),
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        spike_frames = Counter(
            "spk2img_spike_frames_received",
            "Spike frames decoded from uploads",
            ("method",),
            registry=self.registry,
        )
        frames = Counter(
            "spk2img_frames_sent",
            "Reconstructed frames sent",
            ("method", "format"),
            registry=self.registry,
        )
        errors = Counter(
            "spk2img_errors",
            "Errors: http (an error response), in_band (an ERRO record), disconnect (the "
            "client left mid-request), slow_upload (408: the upload stalled or trickled), "
            "unread (the client read nothing while its frames filled the response buffer)",
            ("status", "kind"),
            registry=self.registry,
        )
        refused = Counter(
            "spk2img_refused",
            "Requests or connections turned away: busy (no admission left), memory (over the "
            "memory budget), connections (over max_connections), header_timeout (no whole "
            "request head in time)",
            ("reason",),
            registry=self.registry,
        )
        self.requests = BoundedLabels(requests, HTTP_METHODS, (), STATUSES)
        self.latency = BoundedLabels(latency, HTTP_METHODS, ())
        self.spike_frames = BoundedLabels(spike_frames, RECON_METHODS)
        self.frames = BoundedLabels(frames, RECON_METHODS, FORMATS)
        self.errors = BoundedLabels(errors, STATUSES, ERROR_KINDS)
        self.refused = BoundedLabels(refused, REFUSALS)
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
        self.reserved = Gauge(
            "spk2img_reserved_memory_bytes",
            "Memory reserved by the admitted reconstructions (estimates, see memory_budget_bytes)",
            registry=self.registry,
        )
        self.connections = Gauge(
            "spk2img_open_connections",
            "Open HTTP connections",
            registry=self.registry,
        )

    def set_paths(self, paths: tuple[str, ...]) -> None:
        """The route templates the ``path`` label may take (others count as ``unmatched``)."""
        self.paths = frozenset((*paths, "unmatched"))
        self.requests.allowed = (frozenset(HTTP_METHODS), self.paths, frozenset(STATUSES))
        self.latency.allowed = (frozenset(HTTP_METHODS), self.paths)

    def watch_pool(
        self, jobs: Callable[[], int], admitted: Callable[[], int], reserved: Callable[[], int]
    ) -> None:
        """Read the queue depth, admissions and reserved memory from the pool at each scrape."""
        self.queue_depth.set_function(jobs)
        self.admitted.set_function(admitted)
        self.reserved.set_function(reserved)

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
            if path not in self.metrics.paths:
                path = "unmatched"
            method = scope["method"]
            self.metrics.requests.labels(method, path, status).inc()
            self.metrics.latency.labels(method, path).observe(time.perf_counter() - start)
            if status.isdigit() and int(status) >= 400:
                self.metrics.errors.labels(status, "http").inc()
