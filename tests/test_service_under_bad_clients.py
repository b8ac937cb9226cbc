"""The service under hostile and careless clients, over loopback, bounded in count and
time: trickling and stalled uploads, junk labels, half-sent heads, too many connections,
disconnects mid-job, half-close, send-then-read clients and the memory budget."""

from __future__ import annotations

import random
import select
import socket
import string
import threading
import time

import httpx
import pytest
from service_support import (
    OCTET,
    DuplexClient,
    metric_value,
    parse_frames,
    run_app_server,
    stream_bytes,
)

from spk2img.protocol.framing import DoneRecord, ErrorRecord
from spk2img.service.metrics import OTHER, ServiceMetrics

READ_TIMEOUT = 1.0
H, W = 16, 16  # 32 bytes a frame


class SlowModel:
    """The served model, slowed to ``delay`` seconds a call and counting its calls."""

    def __init__(self, model, delay: float):
        self.model, self.delay = model, delay
        self.calls = 0
        self.path, self.metadata, self.input_name = model.path, model.metadata, model.input_name
        self.geometry = model.geometry

    def __call__(self, windows):
        time.sleep(self.delay)
        self.calls += 1
        return self.model(windows)


@pytest.fixture(scope="module")
def guarded(standin_model):
    """One job at a time (capacity 1), short timeouts, few connections, a small buffer and
    memory budget: every limit is cheap to reach."""
    settings = dict(
        threads=1,
        workers=1,
        max_queue=0,
        upload_read_timeout_seconds=READ_TIMEOUT,
        min_upload_bytes_per_second=1000,
        header_timeout_seconds=1.0,
        keep_alive_seconds=1,
        max_connections=24,
        health_port=0,
        response_buffer_bytes=200_000,
        memory_budget_bytes=64 * 2**20,
        read_ahead_bytes=256 * 2**10,
        max_request_seconds=20,
    )
    with run_app_server(standin_model, **settings) as server:
        yield server


def _wait_for(condition, seconds: float = 5.0) -> float:
    """Poll ``condition`` until it holds; the seconds it took (fails after ``seconds``)."""
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < seconds, "condition not reached in time"
        time.sleep(0.01)
    return time.monotonic() - start


def _idle(server) -> bool:
    return server.state.pool.admitted == 0


def _reset(client: DuplexClient, server, slow: SlowModel, within: float) -> tuple[float, int]:
    """Reset ``client``'s connection (RST): the seconds until the server's places are all free
    again (at most ``within``) and the model calls that ran after the reset."""
    client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\0\0\0\0\0\0\0")
    calls_at_reset = slow.calls
    client.close()
    freed = _wait_for(lambda: _idle(server), within)
    return freed, slow.calls - calls_at_reset


def test_a_trickling_upload_gets_408_within_the_timeout_and_frees_its_slot(guarded):
    """One byte every 0.2 s (5 B/s, under the 1000 B/s minimum): 408 JSON after about the read
    timeout; meanwhile /readyz says 503 (the one slot is taken); after it the slot is free."""
    _wait_for(lambda: _idle(guarded))
    before = metric_value(guarded.get("/metrics").text, "spk2img_errors_total", kind="slow_upload")
    client = DuplexClient(guarded.port)
    start = time.monotonic()
    try:
        client.start(f"/v1/reconstruct?height={H}&width={W}&centers=20&method=tfp", length=3200)
        _wait_for(lambda: not _idle(guarded))
        assert guarded.get("/readyz").status_code == 503
        refused = httpx.post(
            guarded.url + f"/v1/reconstruct?height={H}&width={W}&centers=20",
            content=b"\0" * 3200,
            headers=OCTET,
        )
        assert refused.status_code == 503 and refused.headers["retry-after"] == "1"
        while time.monotonic() - start < 5:  # one byte every 0.2 s until the server answers
            try:
                client.send(b"\x01")
            except OSError:
                break
            if select.select([client.sock], [], [], 0.2)[0]:
                break
        elapsed = time.monotonic() - start
        head = client.read_head()
        body = client.read_all()
    finally:
        client.close()
    assert head.status_code == 408 and b"slower than 1000 bytes/s" in body
    assert elapsed < 2 * READ_TIMEOUT + 1
    _wait_for(lambda: _idle(guarded), 2)
    assert guarded.get("/readyz").status_code == 200
    after = metric_value(guarded.get("/metrics").text, "spk2img_errors_total", kind="slow_upload")
    assert after == before + 1
    print(f"\ntrickling upload: 408 after {elapsed:.2f} s (read timeout {READ_TIMEOUT} s)")


def test_a_stalled_upload_after_frames_ends_with_an_in_band_408(guarded):
    _wait_for(lambda: _idle(guarded))
    _, body = stream_bytes(60, H, W, seed=3)
    client = DuplexClient(guarded.port)
    try:
        client.start(f"/v1/reconstruct?height={H}&width={W}&stride=5&method=tfp")
        client.send(body)  # frames come back; then nothing more is sent
        start = time.monotonic()
        assert client.read_head().status_code == 200
        frames, last = parse_frames(client.read_all())
        elapsed = time.monotonic() - start
    finally:
        client.close()
    assert len(frames) == 4 and isinstance(last, ErrorRecord) and last.status == 408
    assert "no upload data for 1 s" in last.detail and elapsed < READ_TIMEOUT + 1
    _wait_for(lambda: _idle(guarded), 2)


def test_metric_labels_stay_bounded_under_random_values(guarded):
    """After 120 junk requests of each kind, 300 more with random methods, paths and parameter
    values add no series: every label is one of a fixed set, unknown values fold into
    'other'."""
    rng = random.Random(16)

    def junk(n: int) -> str:
        return "".join(rng.choice(string.ascii_letters) for _ in range(n))

    def series(text: str) -> set[str]:
        return {line.rpartition(" ")[0] for line in text.splitlines() if not line.startswith("#")}

    # a connection per request: on a kept-alive one, a client stalled past the 1 s header
    # timeout (a loaded machine) would find it closed under its next request
    fresh = httpx.Limits(max_keepalive_connections=0)
    with httpx.Client(base_url=guarded.url, timeout=10, limits=fresh) as client:
        for _ in range(30):  # warm: every kind of request once
            client.request(junk(5).upper(), f"/{junk(8)}")
            client.get(f"/v1/reconstruct?format={junk(4)}")
            client.post(f"/v1/reconstruct?method={junk(4)}&quality={junk(4)}", headers=OCTET)
            client.request("PATCH", f"/v1/models?x={junk(9)}")
        first = series(client.get("/metrics").text)
        for _ in range(100):
            client.request(junk(6).upper(), f"/{junk(12)}/{junk(3)}")
            client.post(f"/v1/reconstruct?format={junk(5)}&centers=1", headers=OCTET)
            client.request("PATCH", f"/v1/models?x={junk(9)}")
        text = client.get("/metrics").text
    assert series(text) == first  # 300 more junk requests: not one new series
    assert f'method="{OTHER}"' in text and 'path="unmatched"' in text
    assert len(text) < 200_000
    print(f"\n/metrics after 600 junk requests: {len(text)} bytes, {len(series(text))} series")


def test_bounded_labels_fold_unknown_values():
    metrics = ServiceMetrics()
    metrics.set_paths(("/v1/reconstruct",))
    for i in range(500):
        metrics.requests.labels(f"M{i}", f"/p{i}", str(i)).inc()
        metrics.frames.labels(f"m{i}", f"f{i}").inc()
        metrics.errors.labels(str(i), f"k{i}").inc()
        metrics.refused.labels(f"r{i}").inc()
    text = metrics.exposition().decode()
    totals = [line for line in text.splitlines() if line.startswith("spk2img_http_requests_total")]
    assert 'spk2img_http_requests_total{method="other",path="other",status="other"}' in text
    assert len(totals) <= 12  # 'other', and the few known statuses that i ran through
    assert 'spk2img_frames_sent_total{format="other",method="other"} 500.0' in text
    assert len(text) < 20_000


def test_half_sent_heads_are_closed_after_the_header_timeout(guarded):
    """40 connections that send half a request line are all closed by the server after the
    1 s header timeout; past 24 open connections a new one is answered 503 and closed."""
    socks = [socket.create_connection(("127.0.0.1", guarded.port), timeout=5) for _ in range(40)]
    try:
        answered_busy = 0
        for sock in socks:
            try:
                sock.sendall(b"POST /v1/recon")
            except OSError:
                pass
        start = time.monotonic()
        for sock in socks:
            data = sock.recv(4096)  # blocks until the server answers or closes
            if data.startswith(b"HTTP/1.1 503"):
                answered_busy += 1
                assert b"24 open connections" in data
            else:
                assert data == b""
        elapsed = time.monotonic() - start
    finally:
        for sock in socks:
            sock.close()
    assert answered_busy >= 40 - 24 and elapsed < 3
    text = guarded.get("/metrics").text
    assert metric_value(text, "spk2img_refused_total", reason="header_timeout") >= 20
    assert metric_value(text, "spk2img_refused_total", reason="connections") >= 16
    _wait_for(lambda: metric_value(guarded.get("/metrics").text, "spk2img_open_connections") <= 1)
    print(
        f"\n40 half-sent heads: {answered_busy} refused at once, the rest closed in {elapsed:.2f} s"
    )


def test_a_disconnect_cancels_the_job_within_one_model_call(guarded):
    """400 frames sent at once, stride 1 (360 windows at 20 ms each: 7 s of work): the client
    resets the connection once 5 windows are done; the job stops within a model call or two,
    its slot frees and the admitted gauge drops."""
    _wait_for(lambda: _idle(guarded))
    network = guarded.state.network
    model = network.predict
    slow = network.predict = SlowModel(model, 0.02)
    try:
        _, body = stream_bytes(400, H, W, seed=9)
        client = DuplexClient(guarded.port)
        target = f"/v1/reconstruct?height={H}&width={W}&stride=1&method=net"
        client.start(target, {**OCTET, "x-spk2img-duplex": "1"}, length=len(body))
        client.send(body)
        _wait_for(lambda: slow.calls >= 5)
        freed, after = _reset(client, guarded, slow, 2)
    finally:
        network.predict = model
    text = guarded.get("/metrics").text
    assert after <= 3 and freed < 0.2, (after, freed)
    assert metric_value(text, "spk2img_admitted_requests") == 0
    assert metric_value(text, "spk2img_errors_total", kind="disconnect") >= 1
    print(f"\ndisconnect: {after} of 360 model calls after the reset, slot free in {freed:.3f} s")


def test_a_send_then_read_client_gets_its_first_frame_at_once_and_its_reset_frees_the_slot(
    guarded,
):
    """The body sent whole before reading (Content-Length, duplex header; 800 frames of 40x50,
    200 KB: several pieces of the server's reads), as curl, requests and browsers send: the
    first frame comes after its window's model call, not after the piece's 260, and a reset
    after it frees the slot within a second (the rest of the body is read ahead, so the
    disconnect is seen)."""
    _wait_for(lambda: _idle(guarded))
    network = guarded.state.network
    model = network.predict
    slow = network.predict = SlowModel(model, 0.02)
    try:
        _, body = stream_bytes(800, 40, 50, seed=12)
        client = DuplexClient(guarded.port)
        target = "/v1/reconstruct?height=40&width=50&stride=1&method=net"
        start = time.monotonic()
        client.start(target, {**OCTET, "x-spk2img-duplex": "1"}, length=len(body))
        client.send(body)
        first = b""
        while len(first) < 8:  # the tag and length of the first record
            first += client.read_some()
        first_frame = time.monotonic() - start
        freed, after = _reset(client, guarded, slow, 5)
    finally:
        network.predict = model
    assert first.startswith(b"FRAM") and first_frame < 1.0, first_frame
    assert freed < 1.0 and after <= 3, (freed, after)
    print(
        f"\nsend-then-read: first frame after {first_frame:.2f} s, slot free {freed:.2f} s "
        f"after the reset ({after} model calls of 760 after it)"
    )


def test_half_close_gets_every_frame_and_the_end_record(guarded):
    _wait_for(lambda: _idle(guarded))
    _, body = stream_bytes(200, H, W, seed=4)
    target = f"/v1/reconstruct?height={H}&width={W}&stride=3&method=net"
    whole = httpx.post(guarded.url + target, content=body, headers=OCTET, timeout=30).content
    client = DuplexClient(guarded.port)
    try:
        client.start(target, length=len(body))
        client.send(body)
        client.sock.shutdown(socket.SHUT_WR)
        assert client.read_head().status_code == 200
        got = client.read_all()
    finally:
        client.close()
    frames, done = parse_frames(got)
    assert got == whole and isinstance(done, DoneRecord) and done.frames == len(frames) == 54


def test_send_then_read_gets_every_frame_or_a_413_naming_the_limit(guarded):
    """httpx sends the whole body before reading. Frames that fit in the response buffer all
    arrive (here 188 KB of frames while the server reads a 64 KB body at 20 ms a window);
    frames that could exceed it are refused up front with 413 naming the limit, unless the
    client says it reads while uploading."""
    _wait_for(lambda: _idle(guarded))
    _, body = stream_bytes(2000, H, W, seed=5)  # 64,000 bytes
    fits = f"/v1/reconstruct?height={H}&width={W}&stride=11&method=net"  # 179 frames x 1052 B
    answer = httpx.post(guarded.url + fits, content=body, headers=OCTET, timeout=30)
    frames, done = parse_frames(answer.content)
    assert answer.status_code == 200 and isinstance(done, DoneRecord)
    assert [f.center for f in frames] == list(range(20, 1980, 11))
    too_many = f"/v1/reconstruct?height={H}&width={W}&stride=1&method=tfp"
    refused = httpx.post(guarded.url + too_many, content=body, headers=OCTET, timeout=30)
    assert refused.status_code == 413
    detail = refused.json()["detail"]
    assert "200000-byte response buffer (response_buffer_bytes)" in detail
    assert "X-Spk2img-Duplex: 1" in detail


def test_a_client_that_never_reads_loses_its_connection_not_the_slot(guarded):
    """A chunked upload whose frames overflow the buffer while the client reads nothing: the
    connection is closed after the read timeout and the slot is free again."""
    _wait_for(lambda: _idle(guarded))
    before = metric_value(guarded.get("/metrics").text, "spk2img_errors_total", kind="unread")
    _, part = stream_bytes(1000, 64, 64, seed=6)  # 512 B a frame; 16 KB float32 frames
    client = DuplexClient(guarded.port, timeout=10)
    client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        client.start("/v1/reconstruct?height=64&width=64&stride=1&method=tfp&window=3")
        sender = threading.Thread(target=_send_quietly, args=(client, part, 16), daemon=True)
        sender.start()
        _wait_for(lambda: not _idle(guarded))
        freed = _wait_for(lambda: _idle(guarded), 5)
    finally:
        client.close()
    after = metric_value(guarded.get("/metrics").text, "spk2img_errors_total", kind="unread")
    assert after == before + 1 and freed < 3
    print(f"\nnever-reading client: connection closed, slot free after {freed:.2f} s")


def _send_quietly(client: DuplexClient, part: bytes, times: int) -> None:
    try:
        for _ in range(times):
            client.send(part)
        client.end()
    except OSError:
        pass


def test_memory_budget_refuses_with_503_and_too_large_frames_with_422(guarded):
    """64 MiB budget: a 50x50 net request reserves about 55 MiB (52x52 as the network pads it),
    so a second one at the same
    time is refused (503, Retry-After); 100x100 frames could never fit (422)."""
    _wait_for(lambda: _idle(guarded))
    capacity = guarded.state.pool.capacity
    guarded.state.pool.capacity = 2  # two places: the budget, not the places, refuses
    try:
        client = DuplexClient(guarded.port)
        client.start("/v1/reconstruct?height=50&width=50&centers=20&method=net", length=313 * 60)
        _wait_for(lambda: not _idle(guarded))
        second = httpx.post(
            guarded.url + "/v1/reconstruct?height=50&width=50&centers=20&method=net",
            content=b"\0" * 313 * 60,
            headers=OCTET,
        )
        reserved = metric_value(guarded.get("/metrics").text, "spk2img_reserved_memory_bytes")
        client.close()
    finally:
        guarded.state.pool.capacity = capacity
    assert second.status_code == 503 and second.headers["retry-after"] == "1"
    assert "memory budget" in second.json()["detail"] and 50 * 2**20 < reserved < 60 * 2**20
    huge = httpx.post(
        guarded.url + "/v1/reconstruct?height=100&width=100&centers=20&method=net",
        content=b"\0" * 1250 * 60,
        headers=OCTET,
    )
    assert huge.status_code == 422 and "memory budget" in huge.json()["detail"]
    _wait_for(lambda: _idle(guarded), 2)


def _held_heads(port: int, count: int) -> list[socket.socket]:
    """``count`` connections to ``port``, each holding a half-sent request head."""
    socks = []
    for _ in range(count):
        socks.append(socket.create_connection(("127.0.0.1", port), timeout=5))
        socks[-1].sendall(b"GET /v1/mod")
    return socks


def test_liveness_and_readiness_get_through_a_flood_of_held_connections(guarded):
    """300 connections holding half-sent heads on the main port (24 let in, the rest refused
    there): the probes' port still answers /healthz and /readyz, and nothing else. The main
    port's cap is then checked apart, once the flood's places are free, behind a burst of 30
    held heads sent well inside the 1 s header timeout (on a loaded machine the flood outlasts
    it: its first places are freed while it is still being refused, and a burst refused then
    holds nothing)."""
    _wait_for(lambda: _idle(guarded))
    probes = f"http://127.0.0.1:{guarded.listeners.health_port}"
    flood = _held_heads(guarded.port, 300)
    try:
        live = httpx.get(probes + "/healthz", timeout=5)
        ready = httpx.get(probes + "/readyz", timeout=5)
        other = httpx.get(probes + "/v1/models", timeout=5)
    finally:
        for sock in flood:
            sock.close()
    assert live.status_code == 200 and live.json() == {"status": "ok"}
    assert ready.status_code == 200 and ready.json()["status"] == "ready"
    assert other.status_code == 404 and "only" in other.json()["detail"]
    _wait_for(lambda: httpx.get(guarded.url + "/healthz", timeout=5).status_code == 200)
    for _ in range(3):  # a burst slower than the header timeout frees its own places: again
        start = time.monotonic()
        burst = _held_heads(guarded.port, 30)
        try:
            main = httpx.get(guarded.url + "/healthz", timeout=5)
        finally:
            for sock in burst:
                sock.close()
        if time.monotonic() - start < 0.5:
            break
        _wait_for(lambda: httpx.get(guarded.url + "/healthz", timeout=5).status_code == 200)
    assert main.status_code == 503  # the main port's cap, as before


def test_readyz_is_503_while_a_typical_request_would_not_be_admitted(guarded):
    """Two places; the budget of 64 MiB is under a 250x400 frame's cost, so one request that
    reserves most of it leaves the service busy for a typical request though a small one would
    still get in."""
    _wait_for(lambda: _idle(guarded))
    pool = guarded.state.pool
    capacity, pool.capacity = pool.capacity, 2
    admission = pool.admit(40 * 2**20)
    try:
        busy = guarded.get("/readyz")
        small = httpx.post(
            guarded.url + f"/v1/reconstruct?height={H}&width={W}&centers=20&method=tfp",
            content=stream_bytes(45, H, W, seed=3)[1],
            headers=OCTET,
        )
    finally:
        admission.close()
        pool.capacity = capacity
    assert busy.status_code == 503 and "busy" in busy.json()["detail"]
    assert small.status_code == 200
    assert guarded.state.typical_request_bytes == 64 * 2**20  # the whole budget at most
    assert guarded.get("/readyz").status_code == 200


def test_readyz_is_503_while_no_job_could_be_admitted(guarded):
    _wait_for(lambda: _idle(guarded))
    admission = guarded.state.pool.admit(2**20)
    try:
        busy = guarded.get("/readyz")
    finally:
        admission.close()
    assert busy.status_code == 503 and "busy" in busy.json()["detail"]
    assert guarded.get("/readyz").status_code == 200


def test_send_then_read_of_the_largest_body_gets_every_frame(service):
    """The shared service's largest body (3,000,000 bytes: 2000 frames of 100x120) sent whole
    by httpx before it reads: 980 uint8 frames (11.8 MB, more than the socket buffers hold)
    all arrive; as float32 (47 MB, over the 32 MiB buffer) it is a 413 naming the limit."""
    _, body = stream_bytes(2000, 100, 120, seed=8)
    assert len(body) == 3_000_000
    target = "/v1/reconstruct?height=100&width=120&stride=2&method=net"
    start = time.monotonic()
    answer = httpx.post(
        service.url + target + "&format=uint8", content=body, headers=OCTET, timeout=60
    )
    elapsed = time.monotonic() - start
    frames, done = parse_frames(answer.content)
    assert answer.status_code == 200 and isinstance(done, DoneRecord)
    assert [f.center for f in frames] == list(range(20, 1980, 2))
    refused = httpx.post(service.url + target, content=body, headers=OCTET, timeout=60)
    assert refused.status_code == 413 and "response_buffer_bytes" in refused.json()["detail"]
    print(f"\nsend-then-read, 3 MB body: {len(answer.content)} bytes of frames in {elapsed:.1f} s")


def test_the_python_client_reads_while_sending_so_large_responses_pass(guarded):
    """spk2img.clients sends X-Spk2img-Duplex: 1: 1960 frames (2 MB, ten times the 200 KB
    response buffer) of a Content-Length upload all arrive."""
    from spk2img.clients import Client

    _wait_for(lambda: _idle(guarded))
    spikes, _ = stream_bytes(2000, H, W, seed=5)
    with Client(guarded.url) as client:
        frames = list(client.reconstruct(spikes, stride=1, method="tfp", window=41))
    assert [k for k, _ in frames] == list(range(20, 1980))
