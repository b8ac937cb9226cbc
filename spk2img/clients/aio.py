"""The asyncio client: :class:`AsyncClient`, the twin of :class:`~spk2img.clients.Client`."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from typing import Any, TypeVar

import httpx

from .base import (
    DEFAULT_WINDOW,
    ClientBase,
    Format,
    Method,
    Quality,
    httpx_errors,
    json_or_raise,
)
from .duplex import stream_frames_async
from .errors import ConnectionFailed, Spk2ImgError
from .protocol import Frame, ReconstructRequest
from .sources import AsyncSource, open_async_upload

T = TypeVar("T")


class AsyncClient(ClientBase):
    """Asyncio client of the spk2img service, with the methods of :class:`~spk2img.clients.Client`
    as coroutines (``reconstruct`` as an async generator). Use ``async with`` or :meth:`aclose`.

    >>> async with AsyncClient("http://127.0.0.1:8000") as client:
    ...     async for center, image in client.reconstruct(camera_frames(), stride=7):
    ...         show(image)
    """

    _http: httpx.AsyncClient
    _http_class = httpx.AsyncClient

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *_exc_info: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Close the connections kept for :meth:`models`, :meth:`health` and :meth:`ready`."""
        await self._http.aclose()

    async def reconstruct(
        self,
        source: AsyncSource,
        height: int | None = None,
        width: int | None = None,
        *,
        centers: Sequence[int] | str | None = None,
        stride: int | None = None,
        method: Method = "net",
        window: int = DEFAULT_WINDOW,
        format: Format = "float32",
        gamma: float | None = None,
        quality: Quality = "best",
        binning: int = 1,
    ) -> AsyncIterator[Frame]:
        """:meth:`Client.reconstruct <spk2img.clients.Client.reconstruct>` as an async generator;
        ``source`` may also be an async iterable of frames. A sync iterable is drawn from in a
        worker thread, so a blocking camera does not block the event loop."""
        upload = await open_async_upload(source, height, width)
        request = ReconstructRequest(
            centers, stride, method, window, format, gamma, quality, binning
        )
        received = False
        attempt = 0
        while True:
            exchange = self._exchange(upload, request)
            try:
                async for frame in stream_frames_async(
                    self.service, exchange, upload.body(), self.timeout, self.connect_timeout
                ):
                    received = True
                    yield frame
                return
            except Spk2ImgError as exc:
                delay = self._stream_retry_delay(attempt, exc, upload, received)
                if delay is None:
                    raise
            await asyncio.sleep(delay)
            attempt += 1

    async def models(self) -> Any:
        """``GET /v1/models``: the served models and their metadata, as the service's JSON."""
        return await self._retrying(self._models_once)

    async def health(self) -> bool:
        """Whether ``GET /healthz`` answers 200 (the process lives); ``False`` if unreachable."""
        return await self._probe("/healthz")

    async def ready(self) -> bool:
        """Whether ``GET /readyz`` answers 200 (model loaded and warm); ``False`` otherwise."""
        return await self._probe("/readyz")

    async def _models_once(self) -> Any:
        return json_or_raise(await self._get("/v1/models"))

    async def _probe(self, path: str) -> bool:
        try:
            return (await self._get(path)).status_code == 200
        except ConnectionFailed:
            return False

    async def _get(self, path: str) -> httpx.Response:
        with httpx_errors(self.service):
            return await self._http.get(self.service.url(path))

    async def _retrying(self, call: Callable[[], Awaitable[T]]) -> T:
        attempt = 0
        while True:
            try:
                return await call()
            except Spk2ImgError as exc:
                delay = self.retry.delay(attempt, exc)
                if delay is None:
                    raise
            await asyncio.sleep(delay)
            attempt += 1
