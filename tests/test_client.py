"""The Python client (``spk2img.clients``) against the real service, served by uvicorn on
127.0.0.1: remote results equal local ones, frames arrive during the upload, service errors
become typed exceptions, 503s and refused connections are retried, the async twin agrees."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from isolation import extra_closure, without_modules

from spk2img.cli import main as cli_main
from spk2img.clients import (
    AsyncClient,
    BadRequest,
    Client,
    ConnectionFailed,
    PayloadTooLarge,
    ServerError,
    Spk2ImgError,
    StreamError,
    Unavailable,
)
from spk2img.clients.errors import error_for_status
from spk2img.clients.retry import RetryPolicy
from spk2img.io.light import to_display
from spk2img.io.spikes import pack_frames, write_spikes
from spk2img.protocol.framing import encode_done
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.stream import bin_frames

SERVER_PACKAGES = {"fastapi", "onnxruntime", "torch", "uvicorn", "starlette"}
"""What the service and training need and the client must not."""

try:
    import uvicorn

    from spk2img.service.app import create_app
    from spk2img.service.settings import ServiceSettings
except ImportError as exc:  # the serve extra is not installed
    SERVICE_MISSING = f"the service cannot be imported ({exc}): pip install -e '.[serve]'"
else:
    SERVICE_MISSING = ""

needs_service = pytest.mark.skipif(bool(SERVICE_MISSING), reason=SERVICE_MISSING)

T, H, W = 160, 24, 40
STRIDE = 7
MAX_FRAMES = 1000
MAX_WINDOW = 101
WAIT_S = 20.0


@pytest.fixture(scope="module")
def spikes() -> np.ndarray:
    """``(T, H, W) uint8`` 0/1: a gradient scene through integrate-and-fire-like sampling."""
    rng = np.random.default_rng(7)
    intensity = np.linspace(0.05, 1.0, H * W).reshape(H, W)
    return (rng.random((T, H, W)) < 0.6 * intensity).astype(np.uint8)


@pytest.fixture(scope="module")
def files(spikes, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("streams")
    paths = {suffix: root / f"rec.{suffix}" for suffix in ("dat", "npy", "npz")}
    for path in paths.values():
        write_spikes(path, spikes)
    return paths


@contextlib.contextmanager
def serve(app) -> Iterator[str]:
    """Serve an ASGI ``app`` with uvicorn on a free port of 127.0.0.1; yield its URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + WAIT_S
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(WAIT_S)


@pytest.fixture(scope="module")
def url(standin_model) -> Iterator[str]:
    """The real service, in process (``net`` runs the TFP-41 stand-in model), ready."""
    settings = ServiceSettings(
        model=standin_model,
        threads=1,
        max_frames=MAX_FRAMES,
        max_window=MAX_WINDOW,
        retry_after_seconds=0,
    )
    with serve(create_app(settings)) as base_url, Client(base_url) as client:
        deadline = time.monotonic() + WAIT_S
        while not client.ready():
            assert time.monotonic() < deadline, "the service did not get ready"
            time.sleep(0.05)
        yield base_url


def collect(frames) -> tuple[np.ndarray, np.ndarray]:
    pairs = list(frames)
    return np.array([k for k, _ in pairs]), np.stack([image for _, image in pairs])


def assert_same_frames(got: list, expected: list) -> None:
    assert [k for k, _ in got] == [k for k, _ in expected]
    np.testing.assert_array_equal(np.stack([i for _, i in got]), np.stack([i for _, i in expected]))


def stride_centers(window: int, stride: int = STRIDE) -> np.ndarray:
    return np.arange(window // 2, T - window // 2, stride)


# --- remote equals local -------------------------------------------------------------------


SOURCES = {
    "dat path": lambda s, f: (f["dat"], H, W),
    "npy path": lambda s, f: (f["npy"], None, None),
    "npz path": lambda s, f: (str(f["npz"]), None, None),
    "dat bytes": lambda s, f: (pack_frames(s), H, W),
    "array": lambda s, f: (s, None, None),
    "frames one by one": lambda s, f: (iter(s), None, None),
    "frame batches": lambda s, f: ((s[i : i + 50] for i in range(0, T, 50)), H, W),
}


@needs_service
@pytest.mark.parametrize("kind", SOURCES)
def test_every_source_gives_the_local_tfp(url, spikes, files, kind):
    source, height, width = SOURCES[kind](spikes, files)
    with Client(url) as client:
        centers, frames = collect(
            client.reconstruct(source, height, width, stride=STRIDE, method="tfp", window=21)
        )
    np.testing.assert_array_equal(centers, stride_centers(21))
    assert frames.dtype == np.float32 and frames.shape == (len(centers), H, W)
    np.testing.assert_array_equal(frames, tfp(spikes, centers, 21))


@needs_service
def test_tfi_net_and_display_formats_equal_local(url, spikes):
    wanted = [20, 64, 99]
    with Client(url) as client:
        _, tfi_frames = collect(client.reconstruct(spikes, centers=wanted, method="tfi"))
        _, net_frames = collect(client.reconstruct(spikes, centers="20,64,99", method="net"))
        _, uint8 = collect(client.reconstruct(spikes, centers=wanted, method="tfp", format="uint8"))
        _, png = collect(
            client.reconstruct(spikes, centers=wanted, method="tfp", format="png", gamma=1.0)
        )
    np.testing.assert_array_equal(tfi_frames, tfi(spikes, wanted, 41))
    np.testing.assert_allclose(net_frames, tfp(spikes, wanted, 41), atol=1e-6)  # TFP stand-in
    np.testing.assert_array_equal(uint8, to_display(tfp(spikes, wanted, 41)))
    np.testing.assert_array_equal(png, to_display(tfp(spikes, wanted, 41), gamma=None))


@needs_service
@pytest.mark.parametrize("selection", ["--stride 9", "--centers 90,40,60"])
def test_cli_url_equals_local(url, files, tmp_path, selection):
    flags = f"--height {H} --width {W} --method tfp --window 31 {selection} --no-progress"
    common = ["reconstruct", str(files["dat"]), *flags.split()]
    assert cli_main([*common, "--out", str(tmp_path / "local.npz")]) == 0
    assert cli_main([*common, "--out", str(tmp_path / "remote.npz"), "--url", url]) == 0
    local, remote = np.load(tmp_path / "local.npz"), np.load(tmp_path / "remote.npz")
    np.testing.assert_array_equal(remote["centers"], local["centers"])
    np.testing.assert_array_equal(remote["frames"], local["frames"])
    assert remote["frames"].dtype == np.float32 and remote["centers"].dtype == np.int64


@needs_service
def test_binning_through_the_client_and_the_cli_equals_local(url, spikes, files, tmp_path):
    wanted = [41, 80, 118]  # binning 2: 83-frame windows
    with Client(url) as client:
        _, frames = collect(client.reconstruct(spikes, centers=wanted, binning=2))
    merged = [bin_frames(spikes[k - 41 : k + 42], 2) for k in wanted]
    expected = np.stack([tfp(m, [20], 41)[0] / 2 for m in merged])  # the TFP-41 stand-in
    np.testing.assert_allclose(frames, expected, atol=1e-6)
    common = ["reconstruct", str(files["npy"]), "--centers", "41,80,118", "--no-progress"]
    out = tmp_path / "remote.npz"
    assert cli_main([*common, "--binning", "2", "--url", url, "--out", str(out)]) == 0
    np.testing.assert_array_equal(np.load(out)["frames"], frames)


@needs_service
def test_cli_url_reports_service_errors_in_one_line(url, files, tmp_path, capsys):
    window = str(MAX_WINDOW + 2)  # valid locally, over the service's limit
    flags = f"--method tfp --window {window} --centers 60 --url {url}"
    code = cli_main(
        ["reconstruct", str(files["npy"]), "--out", str(tmp_path / "x.npz"), *flags.split()]
    )
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert len(err.splitlines()) == 1 and f"window {window} is over the limit" in err


# --- duplex --------------------------------------------------------------------------------


def gated_frames(spikes: np.ndarray, gate: threading.Event) -> Iterator[np.ndarray]:
    """Yield the frames one by one, but after frame 60 only once ``gate`` is set: a camera
    whose later frames exist only after the first reconstruction came back."""
    for index, frame in enumerate(spikes):
        if index == 60:
            assert gate.wait(WAIT_S), "no frame came back while the upload was going on"
        yield frame


@needs_service
def test_frames_arrive_while_the_upload_goes_on(url, spikes):
    gate = threading.Event()
    received = []
    with Client(url) as client:
        for center, _ in client.reconstruct(gated_frames(spikes, gate), stride=10, method="tfp"):
            received.append(center)
            gate.set()
    assert received == list(stride_centers(41, 10))


@needs_service
def test_async_client_streams_during_the_upload_and_agrees(url, spikes):
    async def run() -> tuple[list[list], list]:
        gate = asyncio.Event()

        async def camera():
            for index, frame in enumerate(spikes):
                if index == 60:
                    await asyncio.wait_for(gate.wait(), WAIT_S)
                yield frame

        async with AsyncClient(url) as client:
            live = []
            async for center, image in client.reconstruct(camera(), stride=10, method="tfp"):
                live.append((center, image))
                gate.set()
            whole = [pair async for pair in client.reconstruct(spikes, stride=10, method="tfp")]
            threaded = [
                pair async for pair in client.reconstruct(iter(spikes), stride=10, method="tfp")
            ]
            status = [await client.health(), await client.ready(), await client.models()]
            return [live, whole, threaded], status

    results, (health, ready, models) = asyncio.run(run())
    with Client(url) as client:
        expected = list(client.reconstruct(spikes, stride=10, method="tfp"))
    for got in results:
        assert_same_frames(got, expected)
    assert health and ready and models["models"][0]["window"] == 41


@needs_service
def test_a_failing_source_is_raised_and_an_abandoned_stream_is_let_go(url, spikes):
    def broken_camera():
        yield from spikes[:80]
        raise RuntimeError("camera unplugged")

    with Client(url) as client:
        with pytest.raises(RuntimeError, match="camera unplugged"):
            list(client.reconstruct(broken_camera(), stride=10, method="tfp"))
        stream = client.reconstruct(spikes, stride=10, method="tfp")
        assert next(stream)[0] == 20
        stream.close()  # abandoned: the service stops the work and frees its place
        assert len(list(client.reconstruct(spikes, stride=10, method="tfp"))) == 12


# --- errors --------------------------------------------------------------------------------


@needs_service
@pytest.mark.parametrize(
    ("request_kwargs", "error", "status", "message"),
    [
        ({"centers": [40], "stride": 5}, BadRequest, 422, "exactly one of centers and stride"),
        ({"centers": [150]}, BadRequest, 422, "no full 41-frame window"),
        ({"stride": 5, "method": "bogus"}, BadRequest, 422, "method"),
        ({"stride": 5, "window": 40, "method": "tfp"}, BadRequest, 422, "odd"),
        ({"stride": 5, "source": "partial frame"}, BadRequest, 422, "not a whole number"),
        ({"stride": 5, "source": "too many frames"}, PayloadTooLarge, 413, f"{MAX_FRAMES} frames"),
        ({"stride": 5, "base": "/nowhere"}, BadRequest, 404, "Not Found"),
    ],
)
def test_service_errors_become_typed_exceptions(
    url, spikes, request_kwargs, error, status, message
):
    kwargs = dict(request_kwargs)
    source = {
        None: spikes,
        "partial frame": pack_frames(spikes)[:-1],
        "too many frames": np.concatenate([spikes] * 7),
    }[kwargs.pop("source", None)]
    with Client(url + kwargs.pop("base", ""), retries=0) as client:
        with pytest.raises(error) as caught:
            list(client.reconstruct(source, H, W, **kwargs))
    assert caught.value.status == status and message in caught.value.detail


@needs_service
def test_error_after_the_first_frame_is_a_stream_error(url, spikes):
    received = []
    with Client(url) as client, pytest.raises(StreamError) as caught:
        for center, _ in client.reconstruct(iter(spikes), centers=[20, 1000], method="tfp"):
            received.append(center)
    assert received == [20]
    assert caught.value.status == 422 and "centre 1000" in caught.value.detail


@pytest.mark.parametrize(
    ("status", "error"),
    [
        *((s, BadRequest) for s in (400, 404, 405, 408, 415, 422)),
        (413, PayloadTooLarge),
        (503, Unavailable),
        (429, Unavailable),
        (500, ServerError),
        (502, ServerError),
    ],
)
def test_status_mapping(status, error):
    exc = error_for_status(status, b'{"detail": "what went wrong"}', "3")
    assert type(exc) is error and exc.status == status and exc.detail == "what went wrong"
    assert "what went wrong" in str(exc)


def test_validation_lists_become_one_line():
    body = b'{"detail": [{"loc": ["query", "height"], "msg": "Field required"}]}'
    assert error_for_status(422, body).detail == "query.height: Field required"


def test_retry_policy_backs_off_and_honours_retry_after():
    policy = RetryPolicy(retries=3, backoff=0.5, max_delay=1.5)
    refused = ConnectionFailed("refused")
    assert [policy.delay(n, refused) for n in range(4)] == [0.5, 1.0, 1.5, None]
    assert policy.delay(0, Unavailable("busy", retry_after=0.0)) == 0.0
    assert policy.delay(0, BadRequest("no", 422)) is None


class BusyProxy:
    """A TCP proxy to ``target`` that answers its first ``busy`` connections itself with
    ``503`` and ``Retry-After: 0`` (after reading the request, as a server that is full would)."""

    RESPONSE = (
        b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
        b"Retry-After: 0\r\nContent-Length: 20\r\nConnection: close\r\n\r\n"
        b'{"detail": "busy!"}\n'
    )

    def __init__(self, target: str, busy: int):
        self.target_port = int(target.rsplit(":", 1)[1])
        self.busy, self.connections = busy, 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)

    def __enter__(self) -> str:
        self._thread.start()
        self._server = self._call(asyncio.start_server(self._handle, "127.0.0.1", 0))
        return f"http://127.0.0.1:{self._server.sockets[0].getsockname()[1]}"

    def __exit__(self, *exc_info: object) -> None:
        self._call(self._shutdown())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(WAIT_S)
        self._loop.close()

    def _call(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(WAIT_S)

    async def _shutdown(self) -> None:
        self._server.close()
        others = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        with contextlib.closing(writer):
            if self.connections <= self.busy:
                await reader.readuntil(b"\r\n\r\n")
                writer.write(self.RESPONSE)
                await writer.drain()
                return
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
            with contextlib.closing(up_writer):
                await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    with contextlib.suppress(OSError):
        while data := await reader.read(1 << 16):
            writer.write(data)
            await writer.drain()
        writer.write_eof()


@needs_service
def test_503_is_retried_then_succeeds(url, spikes):
    with Client(url) as client:
        expected = list(client.reconstruct(spikes, stride=STRIDE, method="tfp"))
    proxy = BusyProxy(url, busy=2)
    with proxy as proxy_url, Client(proxy_url, retries=2, backoff=10.0) as client:
        started = time.monotonic()
        got = list(client.reconstruct(spikes, stride=STRIDE, method="tfp"))
        assert time.monotonic() - started < 5.0  # Retry-After: 0, not the 10 s backoff
    assert proxy.connections == 3
    assert_same_frames(got, expected)


@needs_service
def test_503_after_the_last_retry_is_raised(url, spikes):
    proxy = BusyProxy(url, busy=10)
    with proxy as proxy_url, Client(proxy_url, retries=1) as client:
        with pytest.raises(Unavailable) as caught:
            list(client.reconstruct(spikes, stride=STRIDE, method="tfp"))
        assert asyncio.run(_async_models_error(proxy_url)) is Unavailable
    assert proxy.connections == 4  # two attempts each
    assert caught.value.retry_after == 0.0 and caught.value.detail == "busy!"


async def _async_models_error(url: str) -> type[Spk2ImgError]:
    async with AsyncClient(url, retries=1) as client:
        try:
            await client.models()
        except Spk2ImgError as exc:
            return type(exc)
    raise AssertionError("models() did not fail")


def test_refused_connections_are_retried_then_raised(spikes):
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    with sock, Client(url, retries=2, backoff=0.01) as client:
        started = time.monotonic()
        with pytest.raises(ConnectionFailed, match="cannot connect"):
            list(client.reconstruct(spikes, stride=STRIDE, method="tfp"))
        assert time.monotonic() - started >= 0.03  # 0.01 + 0.02 s of backoff
        assert not client.health() and not client.ready()


def test_a_silent_service_times_out(spikes):
    with socket.create_server(("127.0.0.1", 0)) as silent:  # listens, never answers
        url = f"http://127.0.0.1:{silent.getsockname()[1]}"
        with Client(url, timeout=0.2, retries=0) as client:
            with pytest.raises(ConnectionFailed, match="no response .* for 0.2 s"):
                list(client.reconstruct(spikes[:50], stride=STRIDE, method="tfp"))


FRAMES_HEAD = b"HTTP/1.1 200 OK\r\nContent-Type: application/x-spk2img-frames\r\n"


@pytest.mark.parametrize(
    ("reply", "error", "message"),
    [
        (b"", ConnectionFailed, "closed the connection before answering"),
        (FRAMES_HEAD + b"Transfer-Encoding: chunked\r\n\r\n", ConnectionFailed, "in the middle"),
        (b"garbage\r\n\r\n", ConnectionFailed, "broken response"),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nhi", StreamError, "expected a"),
        (FRAMES_HEAD + b"Content-Length: 8\r\n\r\nXXXX\0\0\0\0", StreamError, "record tag"),
        (FRAMES_HEAD + b"Content-Length: 0\r\n\r\n", StreamError, "without a DONE"),
        (FRAMES_HEAD + b"Content-Length: 21\r\n\r\n" + encode_done(3), StreamError, "sent 0"),
    ],
)
def test_broken_responses_raise_typed_errors(spikes, reply, error, message):
    with socket.create_server(("127.0.0.1", 0)) as server:
        answering = threading.Thread(target=_answer_once, args=(server, reply), daemon=True)
        answering.start()
        with Client(f"http://127.0.0.1:{server.getsockname()[1]}", retries=0) as client:
            with pytest.raises(error, match=message):
                list(client.reconstruct(spikes[:50], stride=STRIDE, method="tfp"))
        answering.join(WAIT_S)


def _answer_once(server: socket.socket, reply: bytes) -> None:
    """Read a request, send ``reply``, and close once the client has finished sending."""
    conn, _ = server.accept()
    with conn:
        conn.recv(1 << 16)
        conn.sendall(reply)
        conn.shutdown(socket.SHUT_WR)
        conn.settimeout(WAIT_S)
        while conn.recv(1 << 16):
            pass


def test_bad_sources_fail_before_connecting(spikes):
    with Client("http://127.0.0.1:9", retries=0) as client:
        with pytest.raises(ValueError, match="height and width"):
            list(client.reconstruct(pack_frames(spikes), stride=STRIDE))
        with pytest.raises(ValueError, match="given for frames of 24x40"):
            list(client.reconstruct(spikes, 25, W, stride=STRIDE))
        with pytest.raises(TypeError, match="cannot upload"):
            list(client.reconstruct(12, stride=STRIDE))


def test_the_client_imports_nothing_of_the_server():
    heavy = ("spk2img.service", "fastapi", "starlette", "onnxruntime", "torch", "uvicorn")
    code = (
        "import sys, spk2img.clients, spk2img.clients.remote\n"
        f"print([m for m in sys.modules if m.startswith({heavy!r})])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_client_extra_pulls_in_no_server_dependency():
    """``pip install ".[client]"`` needs none of the service's or training's packages."""
    closure = extra_closure("client")
    assert {"httpx", "h11", "numpy"} <= closure
    assert not closure & SERVER_PACKAGES, closure & SERVER_PACKAGES


@needs_service
def test_the_client_alone_reconstructs_like_the_local_cli(url, spikes, files, tmp_path):
    """``spk2img reconstruct --url`` in a process where the server's packages cannot be imported
    (as after ``pip install ".[client]"``) gives the local result."""
    env = without_modules(tmp_path / "block", SERVER_PACKAGES)
    code = (
        "import importlib, spk2img.clients, spk2img.cli\n"
        "for m in ('fastapi', 'onnxruntime', 'torch', 'uvicorn', 'starlette'):\n"
        "    try: importlib.import_module(m); print(m)\n"
        "    except ModuleNotFoundError: pass"
    )
    absent = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True, env=env
    )
    assert absent.stdout.strip() == ""
    out = tmp_path / "remote.npz"
    flags = f"--method tfp --stride {STRIDE} --no-progress --url {url}"
    command = [sys.executable, "-m", "spk2img", "reconstruct", files["npz"], "--out", out]
    subprocess.run([*command, *flags.split()], check=True, capture_output=True, env=env)
    remote = np.load(out)
    np.testing.assert_array_equal(remote["centers"], stride_centers(41))
    np.testing.assert_array_equal(remote["frames"], tfp(spikes, stride_centers(41), 41))
