"""What :class:`~spk2img.clients.Client` and :class:`~spk2img.clients.AsyncClient` share:
settings, request building, retry decisions and the reading of plain JSON responses."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any, Literal

import httpx

from spk2img.runtime.methods import DEFAULT_TFP_WINDOW

from .errors import ConnectionFailed, Spk2ImgError, error_for_status
from .protocol import Exchange, ReconstructRequest, ServiceURL
from .retry import RetryPolicy
from .sources import Upload

Method = Literal["net", "tfp", "tfi"]
Format = Literal["float32", "uint8", "png"]
Quality = Literal["best", "balanced", "fast"]
DEFAULT_WINDOW = DEFAULT_TFP_WINDOW


class ClientBase:
    """Settings of a client of the spk2img service.

    Args:
        base_url: where the service listens, ``http://HOST:PORT`` (plain HTTP).
        timeout: seconds one network operation may take — sending a chunk of the upload or
            waiting for the next bytes of a response (``None``: no limit). The network method on
            a CPU takes tens of seconds a frame, hence the generous default.
        connect_timeout: seconds connecting may take.
        retries: how many times a failed connection or a 503 is tried again (0: never).
        backoff: seconds before the first retry, doubled for each next one, capped at 30 s; a
            503's ``Retry-After`` replaces it.
    """

    _http_class: type[httpx.Client] | type[httpx.AsyncClient]
    """The httpx client of the plain JSON requests (:meth:`models`, :meth:`health`, ...)."""

    def __init__(
        self,
        base_url: str,
        *,
        timeout: float | None = 300.0,
        connect_timeout: float | None = 10.0,
        retries: int = 3,
        backoff: float = 0.5,
    ):
        self.service = ServiceURL.parse(base_url)
        self.timeout, self.connect_timeout = timeout, connect_timeout
        self.retry = RetryPolicy(retries, backoff)
        self._http = self._http_class(timeout=httpx.Timeout(timeout, connect=connect_timeout))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.service)!r})"

    def _exchange(self, upload: Upload, request: ReconstructRequest) -> Exchange:
        """A fresh exchange (one per attempt) sending ``upload`` with ``request``."""
        target = self.service.target("/v1/reconstruct", request.params(upload))
        return Exchange(self.service, target, upload.nbytes)

    def _stream_retry_delay(
        self, attempt: int, error: Spk2ImgError, upload: Upload, received: bool
    ) -> float | None:
        """Seconds before trying a reconstruction again, or ``None`` to raise ``error``: never
        once a frame was received or when the upload cannot be sent again."""
        if received or not upload.replayable:
            return None
        return self.retry.delay(attempt, error)


@contextlib.contextmanager
def httpx_errors(service: ServiceURL) -> Iterator[None]:
    """Turn httpx's transport errors into :class:`ConnectionFailed`."""
    try:
        yield
    except httpx.TimeoutException as exc:
        raise ConnectionFailed(f"{service} timed out: {exc!r}") from exc
    except httpx.TransportError as exc:
        raise ConnectionFailed(f"cannot reach {service}: {exc}") from exc


def json_or_raise(response: httpx.Response) -> Any:
    """The JSON of a 2xx ``response``; else raise its typed error."""
    if not response.is_success:
        raise error_for_status(
            response.status_code, response.content, response.headers.get("retry-after")
        )
    return response.json()
