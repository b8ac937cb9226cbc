"""Python client of the spk2img service: :class:`Client` (blocking) and :class:`AsyncClient`.

Light to install (``pip install "spk2img[client]"``: numpy, httpx): nothing here imports the
service, onnxruntime, torch or fastapi. See ``docs/client.md``.
"""

from .aio import AsyncClient
from .errors import (
    BadRequest,
    ConnectionFailed,
    PayloadTooLarge,
    ServerError,
    Spk2ImgError,
    StreamError,
    Unavailable,
)
from .protocol import Frame
from .retry import RetryPolicy
from .sync import Client

__all__ = [
    "AsyncClient",
    "BadRequest",
    "Client",
    "ConnectionFailed",
    "Frame",
    "PayloadTooLarge",
    "RetryPolicy",
    "ServerError",
    "Spk2ImgError",
    "StreamError",
    "Unavailable",
]
