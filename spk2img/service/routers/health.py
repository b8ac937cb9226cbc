"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ..schemas import ErrorDetail, Ready, Status
from ..state import Service

router = APIRouter(tags=["health"])
# the probes answer HEAD as GET without the body (uptime monitors and load balancers send it);
# the OpenAPI description lists GET only


@router.head("/healthz", include_in_schema=False)
@router.get("/healthz")
def healthz() -> Status:
    """200 while the process lives."""
    return Status(status="ok")


@router.head("/readyz", include_in_schema=False)
@router.get(
    "/readyz",
    responses={
        503: {
            "model": ErrorDetail,
            "description": "loading or warming up the model, or busy: no request could be "
            "admitted now",
        }
    },
)
def readyz(service: Service) -> Ready:
    """200 once the model is loaded and warmed while a typical request (one 250x400 frame of
    the network) would be admitted, with the device and onnxruntime provider it runs on; 503
    (with ``Retry-After``) before, and while every place, or too much of the memory budget for
    such a request, is taken."""
    if not service.ready:
        raise service.unavailable()
    if service.pool.full(service.typical_request_bytes):
        raise service.busy()
    model = service.network.predict
    return Ready(status="ready", device=model.device, provider=model.provider)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
)
def metrics(service: Service) -> Response:
    """Requests, latency, frames, errors, queue depth and admitted requests."""
    return Response(service.metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
