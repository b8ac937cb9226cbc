"""Full-duplex HTTP/1.1 for ``POST /v1/reconstruct``: the body goes out while frames come in.

The sync client reads the response in the caller's thread while a background thread sends the
body; the async client reads it in the async generator while a task sends the body. Both speak
through an :class:`~spk2img.clients.protocol.Exchange` over one plain TCP connection.

When the body itself fails (the source raised — a camera iterator, a malformed frame), the
connection is aborted and that exception, not the connection error it causes, is raised. When
sending fails because the service stopped reading (it answered early, e.g. with a 4xx), the
sender just stops: the response says why.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from collections.abc import AsyncIterator, Iterator

from .errors import ConnectionFailed, Spk2ImgError
from .protocol import Exchange, Frame, ServiceURL

READ_BYTES = 1 << 16
STOP_WAIT_S = 1.0
"""How long closing waits for the sender thread (it may be blocked in a live source)."""


def stream_frames(
    service: ServiceURL,
    exchange: Exchange,
    body: Iterator[bytes],
    timeout: float | None,
    connect_timeout: float | None,
) -> Iterator[Frame]:
    """Send ``exchange``'s request with ``body`` from a thread; yield frames as they arrive.

    ``timeout`` (seconds, ``None`` for none) bounds each send and each wait for response bytes;
    ``connect_timeout`` bounds connecting. Raises the errors of :mod:`spk2img.clients.errors`.
    """
    sock = _connect(service, connect_timeout)
    sock.settimeout(timeout)
    sender = _BodySender(sock, exchange, body)
    try:
        try:
            sock.sendall(exchange.head())
            sender.start()
            while not exchange.complete:
                yield from exchange.receive(_recv(sock, service, timeout))
        except Spk2ImgError as exc:
            if sender.failure is not None:
                raise sender.failure from exc
            raise
        except OSError as exc:  # sending the head failed
            raise ConnectionFailed(f"lost the connection to {service}: {exc}") from exc
    finally:
        sender.stop()
        sock.close()


def _connect(service: ServiceURL, timeout: float | None) -> socket.socket:
    try:
        sock = socket.create_connection((service.host, service.port), timeout=timeout)
    except OSError as exc:
        raise ConnectionFailed(f"cannot connect to {service}: {exc}") from exc
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # live frames go out at once
    return sock


def _recv(sock: socket.socket, service: ServiceURL, timeout: float | None) -> bytes:
    try:
        return sock.recv(READ_BYTES)
    except TimeoutError as exc:
        raise ConnectionFailed(f"no response from {service} for {timeout} s") from exc
    except OSError as exc:
        raise ConnectionFailed(f"lost the connection to {service}: {exc}") from exc


class _BodySender(threading.Thread):
    """Sends the body chunks, then the end of the body; records a failure of the source."""

    def __init__(self, sock: socket.socket, exchange: Exchange, body: Iterator[bytes]):
        super().__init__(name="spk2img-upload", daemon=True)
        self._sock, self._exchange, self._body = sock, exchange, body
        self._stopping = threading.Event()
        self.failure: Exception | None = None

    def run(self) -> None:
        try:
            for chunk in self._body:
                if not self._send(self._exchange.data(chunk)):
                    return
            self._send(self._exchange.end())
        except Exception as exc:  # the source failed, or h11 refused its bytes
            self.failure = exc
            self._abort()

    def _send(self, data: bytes) -> bool:
        """Send ``data``; ``False`` once stopped or the connection is gone."""
        if self._stopping.is_set():
            return False
        try:
            self._sock.sendall(data)
        except OSError:
            return False
        return True

    def _abort(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)

    def stop(self) -> None:
        """Stop sending (the response is over or abandoned) and wait briefly for the thread."""
        self._stopping.set()
        if self.is_alive():
            self._abort()
            self.join(STOP_WAIT_S)


async def stream_frames_async(
    service: ServiceURL,
    exchange: Exchange,
    body: Iterator[bytes] | AsyncIterator[bytes],
    timeout: float | None,
    connect_timeout: float | None,
) -> AsyncIterator[Frame]:
    """:func:`stream_frames` on asyncio: a task sends ``body`` (a sync iterator is advanced in a
    worker thread, so a blocking source does not block the event loop)."""
    try:
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(service.host, service.port), connect_timeout
        )
    except OSError as exc:  # TimeoutError included
        raise ConnectionFailed(f"cannot connect to {service}: {exc!r}") from exc
    writer.write(exchange.head())
    sender = asyncio.create_task(_send_body(writer, exchange, body, timeout))
    try:
        try:
            while not exchange.complete:
                for frame in exchange.receive(await _read(reader, service, timeout)):
                    yield frame
        except Spk2ImgError as exc:
            failure = _failure(sender)
            if failure is not None:
                raise failure from exc
            raise
    finally:
        sender.cancel()
        _failure(sender)
        writer.close()


async def _read(reader: asyncio.StreamReader, service: ServiceURL, timeout: float | None) -> bytes:
    try:
        return await asyncio.wait_for(reader.read(READ_BYTES), timeout)
    except TimeoutError as exc:
        raise ConnectionFailed(f"no response from {service} for {timeout} s") from exc
    except OSError as exc:
        raise ConnectionFailed(f"lost the connection to {service}: {exc}") from exc


async def _send_body(
    writer: asyncio.StreamWriter,
    exchange: Exchange,
    body: Iterator[bytes] | AsyncIterator[bytes],
    timeout: float | None,
) -> None:
    try:
        async for chunk in _chunks(body):
            if not await _write(writer, exchange.data(chunk), timeout):
                return
        await _write(writer, exchange.end(), timeout)
    except Exception:  # the source failed, or h11 refused its bytes
        writer.transport.abort()
        raise


async def _write(writer: asyncio.StreamWriter, data: bytes, timeout: float | None) -> bool:
    """Write ``data`` and wait for the buffer to drain; ``False`` once the connection is gone."""
    try:
        writer.write(data)
        await asyncio.wait_for(writer.drain(), timeout)
    except OSError:  # TimeoutError included
        return False
    return True


async def _chunks(body: Iterator[bytes] | AsyncIterator[bytes]) -> AsyncIterator[bytes]:
    if isinstance(body, AsyncIterator):
        async for chunk in body:
            yield chunk
        return
    while (chunk := await asyncio.to_thread(next, body, None)) is not None:
        yield chunk


def _failure(sender: asyncio.Task) -> BaseException | None:
    """The sender task's exception once it has failed (retrieving it), else ``None``."""
    if sender.done() and not sender.cancelled():
        return sender.exception()
    return None
