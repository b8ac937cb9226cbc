"""The full-duplex response of ``POST /v1/reconstruct``: it drives ASGI ``receive``/``send``
itself, so frames go out while the body is still coming in (docs/http.md).

Three parts run at once:

* the **upload** (:class:`_Upload`): a task that reads the body up to ``read_ahead_bytes`` ahead
  and watches for the client leaving (the server says so only to a reader, so a body sent
  whole before the client reads is read ahead whole when it fits). A piece that does not come
  within ``upload_read_timeout_seconds``, or an upload slower on average than
  ``min_upload_bytes_per_second``, ends the request with 408. A disconnect cancels the running
  job at once (it stops at its next step: one model call) and frees its place.
* the **job**: decode each piece, then reconstruct it step by step in the pool, one call at a
  time; the records of each step are queued as soon as it ends, so a frame goes out when its
  window is in.
* the **outbox** (:class:`_Outbox`): a task that sends the records. Up to
  ``response_buffer_bytes`` of records wait for a client that is not reading yet (a client that
  sends its whole body before reading), so the upload goes on; past that the job waits for the
  client to read, and a client that reads nothing for ``upload_read_timeout_seconds`` while the
  buffer is full has its connection closed (counted as ``unread``).

The status line goes out with the first record, so an error found before any record is a JSON
4xx; after it an ``ERRO`` record ends the stream. Either way, the rest of a body still coming is
read and dropped for up to :data:`LINGER_SECONDS` before the connection closes: a server that
closes with body bytes unread resets the connection, and the reset can drop the answer before
a client that sends its whole body first gets to read it.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import TypeVar

from starlette.responses import Response
from starlette.types import Receive, Scope, Send

from spk2img.protocol.framing import MEDIA_TYPE, encode_done, encode_error

from .errors import RequestError, as_request_error, error_response
from .inference import Admission
from .metrics import ServiceMetrics
from .reconstruction import StreamJob
from .settings import ServiceSettings

T = TypeVar("T")

LINGER_SECONDS = 2.0
"""How long the rest of a refused body is read (and dropped) before the connection closes."""


class ClientGone(Exception):
    """The client disconnected."""


class SlowUpload(RequestError):
    """The upload stalled or trickled (408)."""


class Unread(Exception):
    """The client read nothing while its frames filled the response buffer."""


class FramesResponse(Response):
    """Streams ``job``'s records while reading the request body (``application/x-spk2img-frames``).

    ``admission`` is closed when the response ends; ``settings.max_request_seconds`` bounds the
    whole exchange.
    """

    media_type = MEDIA_TYPE

    def __init__(
        self,
        job: StreamJob,
        admission: Admission,
        settings: ServiceSettings,
        metrics: ServiceMetrics,
    ):
        self.job, self.admission, self.settings, self.metrics = job, admission, settings, metrics
        self.background = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        settings = self.settings
        upload = _Upload(
            receive,
            settings.upload_read_timeout_seconds,
            settings.min_upload_bytes_per_second,
            self.job.cancel,
            settings.read_ahead_bytes,
        )
        outbox = _Outbox(send, settings.response_buffer_bytes, settings.upload_read_timeout_seconds)
        try:
            async with asyncio.timeout(settings.max_request_seconds):
                run = self.admission.run
                try:
                    while (chunk := await upload.next()) is not None:
                        await upload.unless_gone(run(self.job.feed, chunk))
                        while self.job.pending:
                            await outbox.put(await upload.unless_gone(run(self.job.advance)))
                    await outbox.put(await upload.unless_gone(run(self.job.finish)))
                    await outbox.put([encode_done(outbox.frames)], frames=False)
                except (ClientGone, Unread):
                    raise
                except Exception as exc:  # noqa: BLE001 - every failure is answered
                    await self._fail(scope, receive, send, upload, outbox, as_request_error(exc))
                await upload.unless_gone(outbox.close())
        except ClientGone:
            self.metrics.errors.labels("disconnect", "disconnect").inc()
        except Unread:
            self.metrics.errors.labels("413", "unread").inc()
        except TimeoutError:
            limit = settings.max_request_seconds
            error = RequestError(408, f"the request took over {limit:g} s")
            try:
                async with asyncio.timeout(settings.upload_read_timeout_seconds):
                    await self._fail(scope, receive, send, upload, outbox, error)
                    await outbox.close()
            except (TimeoutError, ClientGone, Unread):
                pass
        finally:
            self.job.cancel()
            self.admission.close()
            upload.stop()
            outbox.stop()
            method = self.job.query.method
            self.metrics.spike_frames.labels(method).inc(self.job.decoder.frames_decoded)
            self.metrics.frames.labels(method, self.job.query.format).inc(outbox.frames)

    async def _fail(
        self,
        scope: Scope,
        receive: Receive,
        send: Send,
        upload: _Upload,
        outbox: _Outbox,
        error: RequestError,
    ) -> None:
        if isinstance(error, SlowUpload):
            self.metrics.errors.labels("408", "slow_upload").inc()
        if not outbox.started:
            headers = dict(error.headers or {})
            await self._linger(upload, error)
            if not upload.complete:  # the rest of the body is not read: close the connection
                headers["Connection"] = "close"
            response = error_response(RequestError(error.status, error.detail, headers))
            await response(scope, receive, send)  # counted by the metrics middleware
            outbox.answered = True
            return
        self.metrics.errors.labels(str(error.status), "in_band").inc()
        await outbox.put([encode_error(error.detail, error.status)], frames=False)
        await self._linger(upload, error)

    @staticmethod
    async def _linger(upload: _Upload, error: RequestError) -> None:
        if error.status != 408:  # a stalled or timed-out upload gets no more time
            await upload.linger(LINGER_SECONDS)


class _Upload:
    """Reads the request body up to ``read_ahead`` bytes ahead of the job, in a task, and
    notices a disconnect at once while it reads (then calls ``on_gone``: the job stops at its
    next step)."""

    def __init__(
        self,
        receive: Receive,
        read_timeout: float,
        min_rate: int,
        on_gone: Callable[[], None],
        read_ahead: int,
    ):
        self._receive, self._on_gone = receive, on_gone
        self.read_timeout, self.min_rate, self.read_ahead = read_timeout, min_rate, read_ahead
        self._pieces: asyncio.Queue[bytes | None] = asyncio.Queue()
        self._ahead = 0  # bytes in _pieces
        self._room = asyncio.Event()
        self._gone = asyncio.Event()
        self._task = asyncio.ensure_future(self._read())
        self.bytes = 0
        self.waited = 0.0
        self.complete = False  # the whole body has been taken by the job

    async def _read(self) -> None:
        more = True
        while True:
            message = await self._receive()
            if message["type"] == "http.disconnect":
                self._gone.set()
                self._on_gone()
                return
            if more:  # after the body, receive() only ever says the client left
                more = message.get("more_body", False)
                piece = message.get("body", b"")
                self._ahead += len(piece)
                self._pieces.put_nowait(piece)
                if not more:
                    self._pieces.put_nowait(None)
                while self._ahead >= self.read_ahead:
                    self._room.clear()
                    await self._room.wait()

    async def next(self) -> bytes | None:
        """The next piece of the body, ``None`` at its end. Raises :class:`ClientGone` or
        :class:`SlowUpload`."""
        wait = self.read_timeout
        if self.min_rate:
            wait = min(wait, self.read_timeout + self.bytes / self.min_rate - self.waited)
        start = time.monotonic()
        try:
            piece = await self.unless_gone(self._get(max(wait, 0)))
        except TimeoutError:
            if wait < self.read_timeout:
                detail = (
                    f"the upload is slower than {self.min_rate} bytes/s "
                    f"({self.bytes} bytes in {self.waited + wait:.0f} s)"
                )
            else:
                detail = f"no upload data for {self.read_timeout:g} s"
            raise SlowUpload(408, detail) from None
        finally:
            self.waited += time.monotonic() - start
        if piece is None:
            self.complete = True
        else:
            self.bytes += len(piece)
            self._ahead -= len(piece)
            self._room.set()
        return piece

    async def _get(self, wait: float) -> bytes | None:
        # Queue.get() is made here, not by the caller: a coroutine made and then dropped when
        # the client has left would warn "never awaited"
        return await asyncio.wait_for(self._pieces.get(), wait)

    async def unless_gone(self, work: Awaitable[T]) -> T:
        """Await ``work`` unless the client disconnects first (then raise :class:`ClientGone`)."""
        task = asyncio.ensure_future(work)
        if self._gone.is_set():
            task.cancel()
            raise ClientGone
        gone = asyncio.ensure_future(self._gone.wait())
        try:
            done, _ = await asyncio.wait((task, gone), return_when=asyncio.FIRST_COMPLETED)
        except BaseException:  # the time ran out, or the server is stopping
            task.cancel()
            raise
        finally:
            gone.cancel()
        if task not in done:
            task.cancel()
            raise ClientGone
        return task.result()

    async def linger(self, seconds: float) -> None:
        """Read and drop the rest of the body for up to ``seconds`` (a refused request's body
        still coming); stop early when it ends, stalls or the client leaves."""
        if self.complete:
            return
        try:
            async with asyncio.timeout(seconds):
                while await self.next() is not None:
                    pass
        except (TimeoutError, ClientGone, SlowUpload):
            pass

    def stop(self) -> None:
        self._task.cancel()


class _Outbox:
    """Sends records from a task; up to ``limit`` bytes of them wait for a slow reader."""

    def __init__(self, send: Send, limit: int, stall: float):
        self._send, self.limit, self.stall = send, limit, stall
        self._records: deque[bytes] = deque()
        self.buffered = 0
        self.frames = 0
        self.started = False  # a record was queued: the status line is (to be) 200
        self.answered = False  # the response was sent otherwise (a JSON error)
        self._wake = asyncio.Event()
        self._progress = asyncio.Event()
        self._closing = False
        self._task: asyncio.Task | None = None

    async def put(self, records: list[bytes], frames: bool = True) -> None:
        """Queue ``records`` (``FRAM`` records unless ``frames`` is false); wait while more
        than ``limit`` bytes are queued. Raises :class:`Unread` when the client reads nothing
        for ``stall`` seconds meanwhile."""
        if not records:
            return
        data = b"".join(records)
        self._records.append(data)
        self.buffered += len(data)
        self.frames += len(records) if frames else 0
        self.started = True
        if self._task is None:
            self._task = asyncio.ensure_future(self._write())
        self._wake.set()
        await self._wait_below(self.limit)

    async def close(self) -> None:
        """Send what is queued and end the response."""
        if self.answered:
            return
        self._closing = True
        if self._task is None:
            self._task = asyncio.ensure_future(self._write())
        self._wake.set()
        while not self._task.done():
            await self._await_progress()
        self._task.result()

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()

    async def _wait_below(self, limit: int) -> None:
        while self.buffered > limit:
            if self._task.done():
                self._task.result()  # raises what the writer raised
            await self._await_progress()

    async def _await_progress(self) -> None:
        """Wait until the writer sends more; :class:`Unread` after ``stall`` seconds without."""
        self._progress.clear()
        try:
            async with asyncio.timeout(self.stall):
                await self._progress.wait()
        except TimeoutError:
            raise Unread from None

    async def _write(self) -> None:
        try:
            await self._send(
                {
                    "type": "http.response.start",
                    "status": 200,
                    "headers": [
                        (b"content-type", MEDIA_TYPE.encode()),
                        (b"cache-control", b"no-store"),
                        (b"x-accel-buffering", b"no"),  # nginx: pass each record on at once
                    ],
                }
            )
            while True:
                while self._records:
                    data = self._records[0]
                    await self._send(
                        {"type": "http.response.body", "body": data, "more_body": True}
                    )
                    self._records.popleft()
                    self.buffered -= len(data)
                    self._progress.set()
                if self._closing:
                    await self._send(
                        {"type": "http.response.body", "body": b"", "more_body": False}
                    )
                    return
                self._wake.clear()
                await self._wake.wait()
        finally:
            self._progress.set()
