"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ..schemas import ErrorDetail, Status
from ..state import Service

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> Status:
    """200 while the process lives."""
    return Status(status="ok")


@router.get(
    "/readyz",
    responses={503: {"model": ErrorDetail, "description": "loading or warming up the model"}},
)
def readyz(service: Service) -> Status:
    """200 once the model is loaded and warmed, 503 (with ``Retry-After``) before."""
    if not service.ready:
        raise service.unavailable()
    return Status(status="ready")


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
)
def metrics(service: Service) -> Response:
    """Requests, latency, frames, errors, queue depth and admitted requests."""
    return Response(service.metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
