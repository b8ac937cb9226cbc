"""The wire protocol without I/O, shared by both clients: where requests go, what they say, and
how a ``POST /v1/reconstruct`` exchange turns bytes into frames or typed errors.

The exchange is HTTP/1.1 through h11 so that the body can go out while the response comes in
(httpx sends the whole body before it reads a response; docs/http.md).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from urllib.parse import urlencode, urlsplit

import h11
import numpy as np

from spk2img import __version__
from spk2img.errors import InputError
from spk2img.protocol.framing import (
    MEDIA_TYPE,
    DoneRecord,
    ErrorRecord,
    FrameRecord,
    FramingError,
    Record,
    RecordParser,
)

from .errors import ConnectionFailed, StreamError, error_for_status
from .sources import Upload

Frame = tuple[int, np.ndarray]
"""``(centre, image)``: the centre's frame index and its ``(H, W)`` image — float32 linear
intensity in [0, 1] for ``format="float32"``, uint8 display values for ``"uint8"``/``"png"``
(read-only: a view of the response; copy it to change it)."""

USER_AGENT = f"spk2img-client/{__version__}"
DUPLEX_HEADER = "X-Spk2img-Duplex"
"""Sent as ``X-Spk2img-Duplex: 1``: this client reads frames while it uploads, so the service
need not refuse a large response that a send-then-read client could deadlock on."""
ERROR_BODY_BYTES = 1 << 14
"""How much of an error response's body is kept for its message."""


@dataclass(frozen=True)
class ServiceURL:
    """Where the service listens: ``http://HOST:PORT[/PREFIX]`` (plain HTTP only)."""

    host: str
    port: int
    netloc: str
    prefix: str

    @classmethod
    def parse(cls, base_url: str) -> ServiceURL:
        parts = urlsplit(base_url)
        if parts.scheme != "http" or not parts.hostname:
            raise InputError(f"the service URL must look like http://HOST:PORT, got {base_url!r}")
        return cls(parts.hostname, parts.port or 80, parts.netloc, parts.path.rstrip("/"))

    def __str__(self) -> str:
        return f"http://{self.netloc}{self.prefix}"

    def url(self, path: str) -> str:
        """The absolute URL of ``path`` on this service."""
        return f"{self}{path}"

    def target(self, path: str, params: dict[str, str] | None = None) -> str:
        """The request target (path and query) of ``path`` on this service."""
        return self.prefix + path + (f"?{urlencode(params, safe=',')}" if params else "")


@dataclass(frozen=True)
class ReconstructRequest:
    """What one ``POST /v1/reconstruct`` asks for (docs/http.md), apart from the upload.

    ``centers`` is a list or ``"40,80"``; ``quality`` and ``binning`` are sent only when they
    are not the defaults (``best``, 1)."""

    centers: Sequence[int] | str | None
    stride: int | None
    method: str
    window: int
    format: str
    gamma: float | None
    quality: str = "best"
    binning: int = 1

    def params(self, upload: Upload) -> dict[str, str]:
        """The request's query for ``upload`` (its frame size goes with it)."""
        params = {
            "height": str(upload.height),
            "width": str(upload.width),
            "method": self.method,
            "window": str(self.window),
            "format": self.format,
        }
        centers = self.centers
        if centers is not None:
            params["centers"] = centers if isinstance(centers, str) else ",".join(map(str, centers))
        if self.stride is not None:
            params["stride"] = str(self.stride)
        if self.gamma is not None:
            params["gamma"] = str(self.gamma)
        if self.quality != "best":
            params["quality"] = self.quality
        if self.binning != 1:
            params["binning"] = str(self.binning)
        return params


class Exchange:
    """One ``POST /v1/reconstruct`` over h11, without I/O: it makes the bytes to send and turns
    received bytes into frames, raising typed errors (:mod:`spk2img.clients.errors`).

    One thread may send (:meth:`head`, :meth:`data`, :meth:`end`) while another receives
    (:meth:`receive`): h11 is not thread-safe, so each call holds a lock.
    """

    def __init__(self, service: ServiceURL, target: str, nbytes: int | None):
        self._service, self._target, self._nbytes = service, target, nbytes
        self._conn = h11.Connection(h11.CLIENT)
        self._lock = threading.Lock()
        self._status: int | None = None
        self._headers: dict[bytes, bytes] = {}
        self._error_body = bytearray()
        self._records = RecordParser()
        self._frames = 0
        self._done = False
        self.complete = False
        """Whether the whole response has been read (a clean ``DONE``)."""

    def head(self) -> bytes:
        """The request line and headers: ``Content-Length`` when the size is known, else chunked."""
        length = (
            [("Content-Length", str(self._nbytes))]
            if self._nbytes is not None
            else [("Transfer-Encoding", "chunked")]
        )
        headers = [
            ("Host", self._service.netloc),
            ("User-Agent", USER_AGENT),
            ("Accept", MEDIA_TYPE),
            ("Content-Type", "application/octet-stream"),
            ("Connection", "close"),
            (DUPLEX_HEADER, "1"),  # it reads while it sends: no response-buffer limit
            *length,
        ]
        return self._send(h11.Request(method="POST", target=self._target, headers=headers))

    def data(self, chunk: bytes) -> bytes:
        """The bytes that send ``chunk`` of the body."""
        return self._send(h11.Data(data=chunk))

    def end(self) -> bytes:
        """The bytes that end the body."""
        return self._send(h11.EndOfMessage())

    def _send(self, event: h11.Event) -> bytes:
        with self._lock:
            return self._conn.send(event) or b""

    def receive(self, data: bytes) -> Iterator[Frame]:
        """Feed bytes read from the connection (``b""`` at its end); yield the frames they
        complete, then raise the typed error if the response reports or is one."""
        for event in self._events(data):
            if isinstance(event, h11.Response):
                self._status, self._headers = event.status_code, dict(event.headers)
                media_type = self._headers.get(b"content-type", b"").split(b";")[0].strip()
                if self._status == 200 and media_type != MEDIA_TYPE.encode():
                    raise StreamError(f"expected a {MEDIA_TYPE} response, got {media_type!r}")
            elif isinstance(event, h11.Data) and self._status == 200:
                yield from self._frames_of(self._parse(event.data))
            elif isinstance(event, h11.Data):
                self._error_body += event.data[: ERROR_BODY_BYTES - len(self._error_body)]
            elif isinstance(event, h11.EndOfMessage):
                self._end_of_response()
            elif isinstance(event, h11.ConnectionClosed):
                raise ConnectionFailed("the service closed the connection before answering")

    def _events(self, data: bytes) -> list[h11.Event]:
        events = []
        with self._lock:
            self._conn.receive_data(data)
            while True:
                try:
                    event = self._conn.next_event()
                except h11.RemoteProtocolError as exc:
                    if data:
                        reason = f"sent a broken response ({exc})"
                    elif self._status is None:
                        reason = "closed the connection before answering"
                    else:
                        reason = "closed the connection in the middle of its response"
                    raise ConnectionFailed(f"the service {reason}") from exc
                if event in (h11.NEED_DATA, h11.PAUSED):
                    return events
                events.append(event)
                if isinstance(event, h11.ConnectionClosed):
                    return events

    def _parse(self, data: bytes) -> list[Record]:
        try:
            return self._records.feed(data)
        except FramingError as exc:
            raise StreamError(f"malformed response: {exc}") from exc

    def _frames_of(self, records: Iterable[Record]) -> Iterator[Frame]:
        for record in records:
            if isinstance(record, FrameRecord):
                self._frames += 1
                yield record.center, record.image
            elif isinstance(record, ErrorRecord):
                raise StreamError(record.detail, record.status)
            elif isinstance(record, DoneRecord):
                if record.frames != self._frames:
                    raise StreamError(
                        f"the service reported {record.frames} frames but sent {self._frames}"
                    )
                self._done = True

    def _end_of_response(self) -> None:
        if self._status != 200:
            retry_after = self._headers.get(b"retry-after", b"").decode() or None
            raise error_for_status(self._status or 0, bytes(self._error_body), retry_after)
        try:
            self._records.finish()
        except FramingError as exc:
            raise StreamError(str(exc)) from exc
        if not self._done:
            raise StreamError("the response ended without a DONE record")
        self.complete = True
