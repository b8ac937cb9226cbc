"""A bounded load test (8 clients, 200 small requests) against a server with a short queue, and
the request time limit."""

from __future__ import annotations

import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import httpx
import psutil
import pytest
from service_support import OCTET, DuplexClient, parse_frames, run_server, stream_bytes

from spk2img.protocol.framing import DoneRecord

CLIENTS, REQUESTS, WARM_UP = 8, 200, 40
H, W, T = 32, 32, 61
_, BODY = stream_bytes(T, H, W, seed=4)
QUERIES = [
    f"height={H}&width={W}&stride=5&method=net",
    f"height={H}&width={W}&stride=5&method=tfp&window=9&format=png",
    f"height={H}&width={W}&centers=20,30,40&method=tfi",
]
RSS_GROWTH_LIMIT = 16 * 2**20


@pytest.fixture(scope="module")
def busy_server(standin_model):
    """Two workers, two queued: a third concurrent request and beyond may get 503."""
    flags = ("--threads", "2", "--workers", "2", "--max-queue", "2")
    with run_server(standin_model, *flags, "--max-request-seconds", "2") as server:
        yield server


def _client_run(url: str, n: int, offset: int) -> Counter:
    outcomes = Counter()
    with httpx.Client(base_url=url, headers=OCTET, timeout=30) as client:
        for i in range(n):
            response = client.post(f"/v1/reconstruct?{QUERIES[(offset + i) % 3]}", content=BODY)
            if response.status_code == 503:
                assert response.headers["retry-after"] == "1" and "busy" in response.text
            else:
                assert response.status_code == 200, response.text
                frames, done = parse_frames(response.content)
                assert isinstance(done, DoneRecord) and done.frames == len(frames) > 0
            outcomes[response.status_code] += 1
    return outcomes


def _load(url: str, total: int) -> Counter:
    per_client = total // CLIENTS
    with ThreadPoolExecutor(CLIENTS) as pool:
        runs = [pool.submit(_client_run, url, per_client, c) for c in range(CLIENTS)]
        return sum((run.result() for run in runs), Counter())


def test_bounded_load_only_intended_503s_and_flat_memory(busy_server):
    server = psutil.Process(busy_server.process.pid)
    start = time.perf_counter()
    warm = _load(busy_server.url, WARM_UP)
    rss_before = server.memory_info().rss
    rest = _load(busy_server.url, REQUESTS - WARM_UP)
    rss_after = server.memory_info().rss
    outcomes = warm + rest
    seconds = time.perf_counter() - start
    print(
        f"\nload: {sum(outcomes.values())} requests in {seconds:.1f} s, {outcomes[200]} ok, "
        f"{outcomes[503]} busy (503); server RSS {rss_before / 2**20:.1f} MiB after the warm-up, "
        f"{rss_after / 2**20:.1f} MiB at the end"
    )
    assert sum(outcomes.values()) == REQUESTS and set(outcomes) <= {200, 503}
    assert outcomes[200] >= REQUESTS // 4
    assert rss_after - rss_before < RSS_GROWTH_LIMIT
    assert busy_server.get("/readyz").status_code == 200
    metrics = busy_server.get("/metrics").text
    assert "spk2img_admitted_requests 0.0" in metrics
    assert "spk2img_inference_queue_depth 0.0" in metrics


def test_a_request_over_the_time_limit_is_408(busy_server):
    client = DuplexClient(busy_server.port)
    try:
        client.start(f"/v1/reconstruct?{QUERIES[0]}")
        client.send(BODY[: 10 * 128])  # then stall
        head = client.read_head()
        assert head.status_code == 408 and b"over 2 s" in client.read_all()
    finally:
        client.close()


def test_a_server_that_cannot_start_is_an_error_with_its_output(tmp_path):
    """The launcher the benchmark and these tests share sees a server exit (rather than waiting
    out its readiness timeout, whose error says "not ready") and quotes the server's message."""
    missing = tmp_path / "missing.onnx"
    with pytest.raises(RuntimeError, match="spk2img serve exited with 2") as failure:
        with run_server(missing):
            pass
    assert "missing.onnx" in str(failure.value)
