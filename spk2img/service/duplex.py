"""The full-duplex response of ``POST /v1/reconstruct``: it drives ASGI ``receive``/``send``
itself, so frames go out while the body is still coming in (docs/http.md).

The loop is: receive a body chunk → decode and reconstruct it in the pool → send the records it
completed → receive the next chunk. Nothing is buffered beyond one chunk and the window, and a
slow reader slows the upload down (uvicorn's flow control). The status line goes out with the
first record, so an error found before the first frame is still a JSON 4xx; after it, an
``ERRO`` record ends the stream. A client that disconnects ends the work at the next step.
"""

from __future__ import annotations

import asyncio

from starlette.responses import Response
from starlette.types import Receive, Scope, Send

from spk2img.core.framing import MEDIA_TYPE, encode_done, encode_error

from .errors import RequestError, as_request_error, error_response
from .inference import Admission
from .metrics import ServiceMetrics
from .reconstruction import StreamJob


class ClientGone(Exception):
    """The client disconnected."""


class FramesResponse(Response):
    """Streams ``job``'s records while reading the request body (``application/x-spk2img-frames``).

    ``admission`` is closed when the response ends; ``seconds`` bounds the whole exchange.
    """

    media_type = MEDIA_TYPE

    def __init__(
        self, job: StreamJob, admission: Admission, seconds: float, metrics: ServiceMetrics
    ):
        self.job, self.admission, self.seconds, self.metrics = job, admission, seconds, metrics
        self.background = None
        self._started = False
        self._frames = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        disconnect: asyncio.Future | None = None  # after the upload: resolves if the client goes
        try:
            async with asyncio.timeout(self.seconds):
                more = True
                while more:
                    message = await receive()
                    if message["type"] == "http.disconnect":
                        raise ClientGone
                    more = message.get("more_body", False)
                    records = await self.admission.run(self.job.feed, message["body"])
                    await self._send_records(send, records)
                disconnect = asyncio.ensure_future(receive())
                records = await _unless_gone(self.admission.run(self.job.finish), disconnect)
                await self._send_records(send, records, disconnect)
                await self._send_last(send, encode_done(self._frames))
        except ClientGone:
            self.metrics.errors.labels("disconnect", "disconnect").inc()
        except TimeoutError:
            error = RequestError(408, f"the request took over {self.seconds:g} s")
            await self._fail(scope, receive, send, error)
        except Exception as exc:  # noqa: BLE001 - every failure is answered, none kills the server
            await self._fail(scope, receive, send, as_request_error(exc))
        finally:
            self.job.cancel()
            self.admission.close()
            if disconnect is not None:
                disconnect.cancel()
            method = self.job.query.method
            self.metrics.spike_frames.labels(method).inc(self.job.decoder.frames_decoded)
            self.metrics.frames.labels(method, self.job.query.format).inc(self._frames)

    async def _start(self, send: Send) -> None:
        if not self._started:
            self._started = True
            headers = [
                (b"content-type", MEDIA_TYPE.encode()),
                (b"cache-control", b"no-store"),
                (b"x-accel-buffering", b"no"),  # nginx: pass each record on at once
            ]
            await send({"type": "http.response.start", "status": 200, "headers": headers})

    async def _send_records(
        self, send: Send, records: list[bytes], disconnect: asyncio.Future | None = None
    ) -> None:
        if not records:
            return
        if disconnect is not None and disconnect.done():
            raise ClientGone
        await self._start(send)
        await send({"type": "http.response.body", "body": b"".join(records), "more_body": True})
        self._frames += len(records)

    async def _send_last(self, send: Send, record: bytes) -> None:
        await self._start(send)
        await send({"type": "http.response.body", "body": record, "more_body": False})

    async def _fail(self, scope: Scope, receive: Receive, send: Send, error: RequestError) -> None:
        if not self._started:
            await error_response(error)(scope, receive, send)  # counted by the metrics middleware
            return
        self.metrics.errors.labels(str(error.status), "in_band").inc()
        await self._send_last(send, encode_error(error.detail, error.status))


async def _unless_gone(work, disconnect: asyncio.Future) -> list[bytes]:
    """Await ``work`` unless the client disconnects first (then raise :class:`ClientGone`)."""
    task = asyncio.ensure_future(work)
    try:
        done, _ = await asyncio.wait((task, disconnect), return_when=asyncio.FIRST_COMPLETED)
    except BaseException:  # the time ran out, or the server is stopping
        task.cancel()
        raise
    if task not in done:
        task.cancel()
        raise ClientGone
    return task.result()
