"""What one app holds between requests, and the dependencies that hand it to routes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request

from spk2img.runtime.loader import LoadedNetwork

from .errors import RequestError
from .inference import InferencePool
from .metrics import ServiceMetrics
from .settings import ServiceSettings


@dataclass
class ServiceState:
    """The app's settings and metrics, and what the lifespan loads: the network and the pool.

    ``ready`` turns true once the model is loaded and warmed; ``waiting_for`` says what a
    not-ready service is waiting for.
    """

    settings: ServiceSettings
    metrics: ServiceMetrics = field(default_factory=ServiceMetrics)
    network: LoadedNetwork | None = None
    """The served network (onnxruntime), with its block encoder and head when they are beside
    it and ``block_reuse`` is on."""
    pool: InferencePool | None = None
    typical_request_bytes: int = 0
    """What a typical request reserves (:func:`~spk2img.service.reconstruction.typical_request_
    bytes`): ``/readyz`` is 200 only while one would be admitted."""
    ready: bool = False
    waiting_for: str = "the model to load"

    def unavailable(self) -> RequestError:
        """The 503 of a service that is not ready."""
        retry = {"Retry-After": str(self.settings.retry_after_seconds)}
        return RequestError(503, f"not ready: waiting for {self.waiting_for}", retry)

    def busy(self) -> RequestError:
        """The 503 of a service that could admit no request now."""
        retry = {"Retry-After": str(self.settings.retry_after_seconds)}
        return RequestError(503, "busy: no reconstruction could be admitted now", retry)


def service_state(request: Request) -> ServiceState:
    return request.app.state.service


def ready_service(state: Annotated[ServiceState, Depends(service_state)]) -> ServiceState:
    """The service, once it is ready (else 503 with ``Retry-After``)."""
    if not state.ready:
        raise state.unavailable()
    return state


def served_network(state: Annotated[ServiceState, Depends(service_state)]) -> LoadedNetwork:
    """The loaded network (503 before the lifespan has loaded it)."""
    if state.network is None:
        raise state.unavailable()
    return state.network


Service = Annotated[ServiceState, Depends(service_state)]
ReadyService = Annotated[ServiceState, Depends(ready_service)]
ServedNetwork = Annotated[LoadedNetwork, Depends(served_network)]
