"""The app factory: ``create_app(settings)`` builds a FastAPI app whose lifespan loads the ONNX
model, starts the inference pool and warms the model up before ``/readyz`` turns 200."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import numpy as np
from fastapi import FastAPI

from spk2img import __version__
from spk2img.core.block_model import OnnxBlockCodec, block_graph_paths
from spk2img.core.onnx_backend import OnnxModel
from spk2img.core.windows import NET_WINDOW

from .errors import install_error_handlers
from .inference import InferencePool
from .metrics import MetricsMiddleware
from .routers import health, models, reconstruct, viewer
from .settings import ServiceSettings
from .state import ServiceState

WARMUP_SIZE = 32
"""Side of the zero window the model runs once before the service reports ready (pixels)."""

logger = logging.getLogger("spk2img.service")


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """A new app serving ``settings`` (default: from the environment)."""
    state = ServiceState(settings or ServiceSettings())
    app = FastAPI(
        title="spk2img",
        version=__version__,
        summary="Spike-camera streams to images, streamed frame by frame (see docs/service.md).",
        lifespan=_lifespan,
    )
    app.state.service = state
    install_error_handlers(app)
    app.add_middleware(MetricsMiddleware, metrics=state.metrics)
    for router in (reconstruct.router, models.router, health.router, viewer.router):
        app.include_router(router)
    state.metrics.set_paths(tuple(getattr(route, "path", "") for route in app.routes))
    return app


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    state: ServiceState = app.state.service
    settings = state.settings
    state.model = await asyncio.to_thread(
        OnnxModel, settings.model_path, settings.intra_op_threads, settings.device
    )  # a GPU device that cannot run here raises: the service does not start
    if state.model.device_note:
        logger.warning("%s", state.model.device_note)
    logger.info("model runs on %s (%s)", state.model.device, state.model.provider)
    parts = block_graph_paths(settings.model_path).values()
    if settings.block_reuse and all(path.is_file() for path in parts):
        state.codec = await asyncio.to_thread(
            OnnxBlockCodec, settings.model_path, settings.intra_op_threads, state.model.device
        )
    pool = InferencePool(settings.job_workers, settings.max_queue, settings.memory_budget_bytes)
    state.pool = pool
    state.metrics.watch_pool(lambda: pool.jobs, lambda: pool.admitted, lambda: pool.reserved)
    warm_up = asyncio.create_task(_warm_up(state))
    try:
        yield
    finally:
        warm_up.cancel()
        state.ready = False
        state.pool.shutdown()


def _warm_up_codec(codec: OnnxBlockCodec) -> None:
    block = np.zeros((codec.block_frames, WARMUP_SIZE, WARMUP_SIZE), np.float32)
    code = codec.encode(block)
    codec.head([code] * codec.num_blocks, WARMUP_SIZE, WARMUP_SIZE)


async def _warm_up(state: ServiceState) -> None:
    """Run the model (and the block encoder and head) once on zeros, then mark the service
    ready."""
    state.waiting_for = "the model to warm up"
    window = np.zeros((1, NET_WINDOW, WARMUP_SIZE, WARMUP_SIZE), np.float32)
    try:
        await state.pool.run(state.model, window)
        if state.codec is not None:
            await state.pool.run(_warm_up_codec, state.codec)
    except Exception as exc:  # noqa: BLE001 - reported by /readyz and the log, never fatal
        logger.exception("the model failed its warm-up")
        state.waiting_for = f"a model that runs (warm-up failed: {exc})"
        return
    state.ready = True
    logger.info("model %s loaded and warmed: ready", state.model.path.name)
