"""The client's exceptions: one class per failure class, each carrying the server's message.

::

    Spk2ImgError            base: .detail (the server's message), .status (HTTP status or None)
    ├── BadRequest          4xx: parameters, sizes, centres, content type (400/404/405/415/422)
    │   └── PayloadTooLarge 413: the upload is over the service's limits
    ├── Unavailable         503 (or 429): busy or not ready; .retry_after in seconds; retried
    ├── ServerError         other 5xx
    ├── StreamError         an in-band error record after frames were sent, or a malformed body
    └── ConnectionFailed    could not connect, the connection dropped or timed out; retried
"""

from __future__ import annotations

import json
from email.utils import parsedate_to_datetime
from time import time

MAX_DETAIL_CHARS = 2000


class Spk2ImgError(Exception):
    """Base of every error the client raises; ``detail`` is the server's message when it sent one
    and ``status`` the HTTP status (``None`` when no status applies, e.g. a refused connection)."""

    def __init__(self, detail: str, status: int | None = None):
        super().__init__(detail if status is None else f"HTTP {status}: {detail}")
        self.detail = detail
        self.status = status


class BadRequest(Spk2ImgError):
    """The service rejected the request before sending a frame (a 4xx other than 429)."""


class PayloadTooLarge(BadRequest):
    """413: the upload is larger than the service accepts."""


class Unavailable(Spk2ImgError):
    """503 (or 429): the service is busy or not ready; ``retry_after`` is its hint in seconds."""

    def __init__(self, detail: str, status: int | None = 503, retry_after: float | None = None):
        super().__init__(detail, status)
        self.retry_after = retry_after


class ServerError(Spk2ImgError):
    """A 5xx other than 503: the service failed."""


class StreamError(Spk2ImgError):
    """The response failed after it started: an in-band ``ERRO`` record (``status`` is the one
    the record gives, e.g. 400 for an upload that ended mid-frame) or a malformed body."""


class ConnectionFailed(Spk2ImgError):
    """No usable connection: refused, reset, closed mid-response, or timed out."""


def error_for_status(status: int, body: bytes, retry_after: str | None = None) -> Spk2ImgError:
    """The exception for an error response of ``status`` with JSON (or text) ``body``."""
    detail = detail_from_body(body) or f"HTTP {status} with no message"
    if status == 413:
        return PayloadTooLarge(detail, status)
    if status in (429, 503):
        return Unavailable(detail, status, parse_retry_after(retry_after))
    if 400 <= status < 500:
        return BadRequest(detail, status)
    if status >= 500:
        return ServerError(detail, status)
    return Spk2ImgError(f"unexpected response: {detail}", status)


def detail_from_body(body: bytes) -> str:
    """The message of an error body: ``{"detail": str}``, FastAPI's validation list
    (``[{"loc": [...], "msg": ...}]``, joined as ``query.height: msg; ...``) or plain text."""
    text = body.decode("utf-8", "replace").strip()
    try:
        detail = json.loads(text)["detail"]
    except (ValueError, TypeError, KeyError):
        return text[:MAX_DETAIL_CHARS]
    if isinstance(detail, list):
        return "; ".join(_validation_message(item) for item in detail)[:MAX_DETAIL_CHARS]
    return str(detail)[:MAX_DETAIL_CHARS]


def _validation_message(item: object) -> str:
    if isinstance(item, dict) and "msg" in item:
        where = ".".join(str(part) for part in item.get("loc", ()))
        return f"{where}: {item['msg']}" if where else str(item["msg"])
    return str(item)


def parse_retry_after(value: str | None) -> float | None:
    """``Retry-After`` as seconds from now (delta-seconds or an HTTP date); ``None`` if absent
    or unreadable."""
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        return max(0.0, parsedate_to_datetime(value).timestamp() - time())
    except (TypeError, ValueError):
        return None
