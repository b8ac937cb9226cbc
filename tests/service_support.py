"""Helpers for the service tests: a real ``spk2img serve`` in a subprocess, and a small h11
client that can read the response while it is still sending the body (full duplex)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h11
import httpx
import numpy as np

from spk2img.bench.serve_process import free_port, serve_process
from spk2img.io.spikes import pack_frames
from spk2img.protocol.framing import DoneRecord, ErrorRecord, FrameRecord, RecordParser

START_SECONDS = 60
OCTET = {"content-type": "application/octet-stream"}


run_server = serve_process
"""A real ``spk2img serve`` in a subprocess (:func:`spk2img.bench.serve_process.serve_process`)."""


def random_stream(frames: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """``(T, H, W)`` uint8 0/1 spikes with a different firing rate in each pixel."""
    rng = np.random.default_rng(seed)
    rate = rng.uniform(0.02, 0.6, (height, width))
    return (rng.random((frames, height, width)) < rate).astype(np.uint8)


def stream_bytes(frames: int, height: int, width: int, seed: int = 0) -> tuple[np.ndarray, bytes]:
    spikes = random_stream(frames, height, width, seed)
    return spikes, pack_frames(spikes)


class DuplexClient:
    """One HTTP/1.1 exchange over h11 on a raw socket: send the body in pieces, read at any time.

    Sending and reading may run in two threads (:meth:`send_in_background`): a client that sends
    a large body without reading a large response would otherwise deadlock with the server.
    """

    def __init__(self, port: int, timeout: float = 20):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.conn = h11.Connection(h11.CLIENT)
        self._lock = threading.Lock()  # guards self.conn; socket I/O happens outside it
        self.response: h11.Response | None = None
        self.ended = False

    def start(self, target: str, headers: dict[str, str] | None = None, length: int | None = None):
        """Send the request head: chunked unless ``length`` (a Content-Length) is given."""
        head = [("host", "127.0.0.1"), *(headers if headers is not None else OCTET).items()]
        head.append(
            ("content-length", str(length))
            if length is not None
            else ("transfer-encoding", "chunked")
        )
        self._send(h11.Request(method="POST", target=target, headers=head))

    def send(self, data: bytes) -> None:
        if data:
            self._send(h11.Data(data=data))

    def end(self) -> None:
        self._send(h11.EndOfMessage())

    def send_in_background(self, data: bytes) -> threading.Thread:
        """Send ``data`` and end the body from another thread; join the thread when done."""

        def send_rest() -> None:
            self.send(data)
            self.end()

        thread = threading.Thread(target=send_rest, daemon=True)
        thread.start()
        return thread

    def read_head(self) -> h11.Response:
        while self.response is None:
            self._next()
        return self.response

    def read_some(self) -> bytes:
        """The next piece of the response body (``b""`` once it has ended)."""
        self.read_head()
        while not self.ended:
            event = self._next()
            if isinstance(event, h11.Data):
                return bytes(event.data)
        return b""

    def read_all(self) -> bytes:
        body = bytearray()
        while piece := self.read_some():
            body += piece
        return bytes(body)

    def close(self) -> None:
        self.sock.close()

    def _send(self, event) -> None:
        with self._lock:
            data = self.conn.send(event)
        self.sock.sendall(data)

    def _next(self):
        while True:
            with self._lock:
                event = self.conn.next_event()
            if event is h11.NEED_DATA:
                data = self.sock.recv(65536)
                with self._lock:
                    self.conn.receive_data(data)
                    closed = not data and self.conn.their_state is not h11.DONE
                if closed:
                    raise ConnectionError("the server closed the connection mid-response")
                continue
            if isinstance(event, h11.Response):
                self.response = event
            elif isinstance(event, h11.EndOfMessage):
                self.ended = True
            return event


def post_chunks(port: int, target: str, chunks: Iterable[bytes], pause: float = 0.0):
    """POST ``chunks`` chunked (``pause`` seconds between them); return (status, headers, body).

    It reads only once the upload is over: keep responses smaller than the socket buffers.
    """
    client = DuplexClient(port)
    try:
        client.start(target)
        for chunk in chunks:
            client.send(chunk)
            if pause:
                time.sleep(pause)
        client.end()
        head = client.read_head()
        return head.status_code, dict(head.headers), client.read_all()
    finally:
        client.close()


def parse_frames(body: bytes) -> tuple[list[FrameRecord], DoneRecord | ErrorRecord]:
    """Split a whole response body into its frames and its last record (DONE or ERRO)."""
    parser = RecordParser()
    records = parser.feed(body)
    parser.finish()
    *frames, last = records
    assert all(isinstance(f, FrameRecord) for f in frames), records
    assert isinstance(last, DoneRecord | ErrorRecord), last
    return frames, last


@dataclass
class AppServer:
    """The service run in this process (uvicorn in a thread, with the server's connection
    limits): its URL, port and app, whose state a test may look at or change."""

    url: str
    port: int
    app: object
    listeners: object

    def get(self, path: str) -> httpx.Response:
        return httpx.get(self.url + path, timeout=10)

    @property
    def state(self):
        return self.app.state.service


@contextmanager
def run_app_server(model: Path, **settings) -> Iterator[AppServer]:
    """Serve ``model`` with ``ServiceSettings(**settings)`` from a thread of this process;
    wait until ``/readyz`` is 200."""
    from spk2img.service.server import Listeners
    from spk2img.service.settings import ServiceSettings

    port = free_port()
    listeners = Listeners(ServiceSettings(model=model, port=port, log_level="warning", **settings))
    thread = threading.Thread(target=listeners.run, daemon=True)
    thread.start()
    running = AppServer(f"http://127.0.0.1:{port}", port, listeners.app, listeners)
    try:
        deadline = time.monotonic() + START_SECONDS
        while True:
            try:
                if running.get("/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline or not thread.is_alive():
                raise RuntimeError("the in-process server did not get ready")
            time.sleep(0.05)
        yield running
    finally:
        listeners.stop()  # no grace for the tests' leftovers
        thread.join(15)


def metric_value(text: str, name: str, **labels: str) -> float:
    """The value of the series ``name{labels}`` in a Prometheus exposition (0 if absent)."""
    for line in text.splitlines():
        if line.startswith("#") or not line.startswith(name):
            continue
        series, _, value = line.rpartition(" ")
        head, _, rest = series.partition("{")
        if head != name:
            continue
        found = dict(part.split("=", 1) for part in rest.rstrip("}").split(",") if "=" in part)
        if all(found.get(k) == f'"{v}"' for k, v in labels.items()):
            return float(value)
    return 0.0
