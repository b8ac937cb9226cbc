"""The app factory: ``create_app(settings)`` builds a FastAPI app whose lifespan loads the ONNX
network (:func:`load_served_network`) unless the app was given one, starts the inference pool
and warms the network up before ``/readyz`` turns 200.

``spk2img serve`` loads the network before the server starts (so a model or device that cannot
run is one line and exit 2) and hands it to the app: the model is loaded once."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from spk2img import __version__
from spk2img.runtime.allocator import map_large_allocations_apart
from spk2img.runtime.loader import LoadedNetwork, load_network

from .errors import install_error_handlers
from .inference import InferencePool
from .memory import budget_problem, container_limit_bytes, resident_bytes
from .metrics import MetricsMiddleware
from .query import single_valued_query
from .reconstruction import typical_request_bytes
from .routers import health, models, reconstruct, viewer
from .security import SecurityHeadersMiddleware
from .settings import ServiceSettings
from .state import ServiceState

logger = logging.getLogger("spk2img.service")


def create_app(
    settings: ServiceSettings | None = None, network: LoadedNetwork | None = None
) -> FastAPI:
    """A new app serving ``settings`` (default: from the environment) with ``network``, one
    loaded by :func:`load_served_network` for these settings (default: the lifespan loads it)."""
    state = ServiceState(settings or ServiceSettings(), network=network)
    app = FastAPI(
        title="spk2img",
        version=__version__,
        summary="Spike-camera streams to images, streamed frame by frame (see docs/service.md).",
        lifespan=_lifespan,
        docs_url=None,  # Swagger UI and ReDoc load from a CDN: /docs is the viewer's API page
        redoc_url=None,
        redirect_slashes=False,  # a redirect would build its Location from the Host header
        dependencies=[Depends(single_valued_query)],
    )
    app.state.service = state
    install_error_handlers(app)
    app.add_middleware(MetricsMiddleware, metrics=state.metrics)
    app.add_middleware(SecurityHeadersMiddleware)
    for router in (reconstruct.router, models.router, health.router, viewer.router):
        app.include_router(router)
    state.metrics.set_paths(tuple(getattr(route, "path", "") for route in app.routes))
    return app


def load_served_network(settings: ServiceSettings) -> LoadedNetwork:
    """The network ``settings`` serve, not yet warmed up (the app warms it in its pool, so that
    ``/readyz`` says when that is done).

    Raises :class:`~spk2img.errors.InputError` for a model that does not load and
    :class:`~spk2img.errors.DeviceError` for a device that cannot run here.
    """
    map_large_allocations_apart()  # freed buffers go back to the system (runtime.allocator)
    return load_network(
        settings.model_path,
        device=settings.device,
        threads=settings.intra_op_threads,
        block_reuse=settings.block_reuse,
        batch=settings.batch,
        self_ensemble=settings.self_ensemble,
        warm_up=False,
    )


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    state: ServiceState = app.state.service
    settings = state.settings
    if state.network is None:  # a GPU that cannot run here: no start
        state.network = await asyncio.to_thread(load_served_network, settings)
    model = state.network.predict
    if model.device_note:
        logger.warning("%s", model.device_note)
    logger.info("model runs on %s (%s)", model.device, model.provider)
    pool = InferencePool(settings.job_workers, settings.max_queue, settings.memory_budget_bytes)
    state.pool = pool
    state.typical_request_bytes = typical_request_bytes(settings, state.network.geometry)
    state.metrics.watch_pool(lambda: pool.jobs, lambda: pool.admitted, lambda: pool.reserved)
    problem = budget_problem(
        settings.memory_budget_bytes, resident_bytes(), container_limit_bytes()
    )
    warm_up = None
    if problem:  # never ready: /readyz and the log say why
        logger.error("%s", problem)
        state.waiting_for = f"a memory budget that fits ({problem})"
    else:
        warm_up = asyncio.create_task(_warm_up(state))
    try:
        yield
    finally:
        if warm_up is not None:
            warm_up.cancel()
        state.ready = False
        state.pool.shutdown()


async def _warm_up(state: ServiceState) -> None:
    """Run the network (and the block encoder and head) once on zeros, then mark the service
    ready."""
    state.waiting_for = "the model to warm up"
    try:
        await state.pool.run(state.network.warm_up)
    except Exception as exc:  # noqa: BLE001 - reported by /readyz and the log, never fatal
        logger.exception("the model failed its warm-up")
        state.waiting_for = f"a model that runs (warm-up failed: {exc})"
        return
    state.ready = True
    logger.info("model %s loaded and warmed: ready", state.network.predict.path.name)
