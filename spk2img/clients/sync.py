"""The blocking client: :class:`Client`."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar, cast

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
from .duplex import stream_frames
from .errors import ConnectionFailed, Spk2ImgError
from .protocol import Frame, ReconstructRequest
from .sources import Source, open_upload

T = TypeVar("T")


class Client(ClientBase):
    """Blocking client of the spk2img service; see :class:`~spk2img.clients.base.ClientBase`
    for the arguments. Use it as a context manager, or call :meth:`close`.

    >>> with Client("http://127.0.0.1:8000") as client:
    ...     for center, image in client.reconstruct("rec.dat", 250, 400, stride=20, method="tfp"):
    ...         print(center, image.shape)
    """

    _http: httpx.Client
    _http_class = httpx.Client

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connections kept for :meth:`models`, :meth:`health` and :meth:`ready`."""
        self._http.close()

    def reconstruct(
        self,
        source: Source,
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
    ) -> Iterator[Frame]:
        """Upload a spike stream and yield ``(centre, image)`` for each requested centre as soon
        as the service sends it — while the upload is still going.

        Args:
            source: a path (``.dat``, ``.npy``, ``.npz``), ``.dat`` bytes, a ``(T, H, W)`` 0/1
                array, or an iterable of ``(H, W)`` / ``(n, H, W)`` 0/1 frames (a live camera;
                drawn from a background thread). See :mod:`spk2img.clients.sources`.
            height, width: frame size in pixels; needed for ``.dat`` paths and bytes, else taken
                from the frames (and checked if given).
            centers: the centre frame indices wanted (a list or ``"40,80"``), or
            stride: every ``stride``-th centre with a full window.
            method: ``"net"`` (the served model, 41-frame windows), ``"tfp"`` or ``"tfi"``.
            window: TFP's window in frames (odd).
            format: ``"float32"`` images are ``(H, W)`` linear intensity in [0, 1] (docs/format.md);
                ``"uint8"`` and ``"png"`` are ``(H, W)`` uint8 display values.
            gamma: display gamma the service applies for ``uint8``/``png``.
            quality: for ``net``: ``"best"`` (the network everywhere), ``"balanced"`` (the
                network only on tiles that move or are dim, TFP elsewhere) or ``"fast"``
                (TFP over the network's 41 frames); see :mod:`spk2img.runtime.adaptive`.
            binning: for ``net`` with quality ``best``, on dim streams: frames merged into each
                of the network's 41 (:func:`spk2img.suggest_binning` picks one; 1: none).

        Nothing happens until iteration starts. Connection failures and 503s are retried (see
        :class:`~spk2img.clients.retry.RetryPolicy`) until the first frame arrives, unless a
        live source has been drawn from. Raises the errors of :mod:`spk2img.clients.errors`,
        and ``InputError`` / ``FileNotFoundError`` for a source that cannot be read.
        """
        upload = open_upload(source, height, width)
        request = ReconstructRequest(
            centers, stride, method, window, format, gamma, quality, binning
        )
        received = False
        attempt = 0
        while True:
            exchange = self._exchange(upload, request)
            body = cast(Iterator[bytes], upload.body())  # open_upload makes no async body
            try:
                for frame in stream_frames(
                    self.service, exchange, body, self.timeout, self.connect_timeout
                ):
                    received = True
                    yield frame
                return
            except Spk2ImgError as exc:
                delay = self._stream_retry_delay(attempt, exc, upload, received)
                if delay is None:
                    raise
            time.sleep(delay)
            attempt += 1

    def models(self) -> Any:
        """``GET /v1/models``: the served models and their metadata, as the service's JSON."""
        return self._retrying(self._models_once)

    def health(self) -> bool:
        """Whether ``GET /healthz`` answers 200 (the process lives); ``False`` if unreachable."""
        return self._probe("/healthz")

    def ready(self) -> bool:
        """Whether ``GET /readyz`` answers 200 (model loaded and warm); ``False`` otherwise."""
        return self._probe("/readyz")

    def _models_once(self) -> Any:
        return json_or_raise(self._get("/v1/models"))

    def _probe(self, path: str) -> bool:
        try:
            return self._get(path).status_code == 200
        except ConnectionFailed:
            return False

    def _get(self, path: str) -> httpx.Response:
        with httpx_errors(self.service):
            return self._http.get(self.service.url(path))

    def _retrying(self, call: Callable[[], T]) -> T:
        attempt = 0
        while True:
            try:
                return call()
            except Spk2ImgError as exc:
                delay = self.retry.delay(attempt, exc)
                if delay is None:
                    raise
            time.sleep(delay)
            attempt += 1
