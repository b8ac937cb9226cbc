"""The service over real HTTP (uvicorn in a subprocess): results, errors, health and metrics."""

from __future__ import annotations

import io
import re
import time

import httpx
import numpy as np
import pytest
from onnx_models import TFP_MODEL_METADATA
from reference import tfp_reference
from service_support import OCTET, DuplexClient, parse_frames, stream_bytes

from spk2img.io.light import to_display
from spk2img.io.spikes import frame_nbytes
from spk2img.protocol.framing import MEDIA_TYPE, ErrorRecord
from spk2img.runtime.methods import build_reconstructor, method_plan
from spk2img.runtime.onnx_backend import OnnxModel
from spk2img.runtime.stream import collect, frame_chunks, run_stream

H, W, T = 16, 24, 100
SPIKES, BODY = stream_bytes(T, H, W, seed=1)


def _npy_upload(spikes: np.ndarray) -> bytes:
    """``spikes`` as a .npy file, zero-padded to whole frames: what a user may post by mistake."""
    buffer = io.BytesIO()
    np.save(buffer, spikes)
    return buffer.getvalue() + bytes(-buffer.tell() % frame_nbytes(H, W))


NPY_BODY = _npy_upload(SPIKES)


def post(service, query: str, body=BODY, headers=OCTET) -> httpx.Response:
    return httpx.post(
        f"{service.url}/v1/reconstruct?{query}", content=body, headers=headers, timeout=30
    )


def local(
    method: str,
    centers: str | None,
    stride: int | None,
    model,
    window: int = 41,
    quality: str = "best",
    binning: int = 1,
):
    """The same reconstruction with spk2img.core, in-process."""
    plan = method_plan(method, centers, stride, window, binning)
    predict = model if method == "net" else None
    recon = build_reconstructor(method, H, W, plan, predict, quality=quality, binning=binning)
    return collect(run_stream(recon, frame_chunks(SPIKES, 7)), H, W)


@pytest.fixture(scope="module")
def model(standin_model):
    return OnnxModel(standin_model, threads=1)


def test_health_readiness_and_models(service):
    assert service.get("/healthz").json() == {"status": "ok"}
    ready = {"status": "ready", "device": "cpu", "provider": "CPUExecutionProvider"}
    assert service.get("/readyz").json() == ready
    answer = service.get("/v1/models").json()
    assert answer["methods"] == ["net", "tfp", "tfi"]
    (info,) = answer["models"]
    assert info["name"] == "tfp41-standin" and info["metadata"] == TFP_MODEL_METADATA
    assert info["window"] == 41 and info["input_name"] == "spikes"
    assert (info["device"], info["provider"]) == ("cpu", "CPUExecutionProvider")
    assert service.get("/docs").status_code == 200
    paths = service.get("/openapi.json").json()["paths"]
    assert {"/v1/reconstruct", "/v1/models", "/healthz", "/readyz", "/metrics"} <= set(paths)
    for path, body in (
        ("/healthz", b'{"status":"ok"}'),
        ("/readyz", service.get("/readyz").content),
    ):
        head = httpx.head(service.url + path, timeout=10)  # as monitors probe: no body
        assert (head.status_code, head.content) == (200, b"")
        assert head.headers["content-length"] == str(len(body))
    assert httpx.head(service.url + "/v1/models", timeout=10).status_code == 405


@pytest.mark.parametrize(
    ("method", "centers", "stride", "window", "quality"),
    [
        ("net", "20,45,79", None, 41, "best"),
        ("net", None, 6, 41, "best"),
        ("net", None, 7, 41, "balanced"),
        ("net", "20,45", None, 41, "fast"),
        ("tfp", "5,50,94", None, 11, "best"),
        ("tfp", None, 9, 41, "best"),
        ("tfi", "20,50,79", None, 41, "best"),
        ("tfi", None, 13, 3, "best"),
    ],
)
def test_results_equal_local(service, model, method, centers, stride, window, quality):
    which = f"centers={centers}" if centers else f"stride={stride}"
    query = f"height={H}&width={W}&method={method}&window={window}&{which}&quality={quality}"
    response = post(service, query)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == MEDIA_TYPE
    frames, done = parse_frames(response.content)
    expected, expected_centers = local(method, centers, stride, model, window, quality)
    assert done.frames == len(frames) == len(expected_centers) > 0
    assert [f.center for f in frames] == expected_centers.tolist()
    for frame, image in zip(frames, expected, strict=True):
        assert frame.format == "float32" and frame.image.shape == (H, W)
        np.testing.assert_array_equal(frame.image, image)


@pytest.mark.parametrize(("binning", "centers"), [(2, "41,50,58"), (1, "20,79")])
def test_binning_merges_frames_like_local(service, model, binning, centers):
    query = f"height={H}&width={W}&method=net&centers={centers}&binning={binning}"
    frames, _ = parse_frames(post(service, query).content)
    expected, expected_centers = local("net", centers, None, model, binning=binning)
    assert [f.center for f in frames] == expected_centers.tolist()
    for frame, image in zip(frames, expected, strict=True):
        half = 41 * binning // 2
        merged = SPIKES[frame.center - half : frame.center + half + 1][: 41 * binning]
        merged = merged.reshape(41, binning, H, W).max(axis=1)
        np.testing.assert_allclose(frame.image, tfp_reference(merged, 20, 41) / binning, atol=1e-6)
        np.testing.assert_array_equal(frame.image, image)


def test_net_with_the_standin_model_is_tfp41(service):
    frames, _ = parse_frames(
        post(service, f"height={H}&width={W}&centers=20,60&method=net").content
    )
    for frame in frames:
        np.testing.assert_allclose(frame.image, tfp_reference(SPIKES, frame.center, 41), atol=1e-6)


@pytest.mark.parametrize(("fmt", "gamma"), [("uint8", 2.2), ("png", 2.2), ("uint8", 1.0)])
def test_display_formats(service, model, fmt, gamma):
    query = f"height={H}&width={W}&centers=20,40&method=tfp&format={fmt}&gamma={gamma}"
    frames, _ = parse_frames(post(service, query).content)
    expected, _ = local("tfp", "20,40", None, model)
    for frame, image in zip(frames, expected, strict=True):
        assert frame.format == fmt and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, to_display(image, gamma))


BAD_REQUESTS = [
    # (query, headers, body, status, words in the detail)
    (f"height={H}&width={W}", OCTET, BODY, 422, "exactly one of centers and stride"),
    (f"height={H}&width={W}&centers=20&stride=3", OCTET, BODY, 422, "exactly one"),
    (f"height={H}&width={W}&centers=20&method=magic", OCTET, BODY, 422, "method"),
    (f"height={H}&width={W}&centers=20&format=jpeg", OCTET, BODY, 422, "format"),
    (f"height={H}&width={W}&centers=20&quality=superb", OCTET, BODY, 422, "quality"),
    (f"height={H}&width={W}&centers=20&method=tfp&quality=fast", OCTET, BODY, 422, "method net"),
    (f"height={H}&width={W}&centers=20&method=tfp&window=4", OCTET, BODY, 422, "odd"),
    (f"height={H}&width={W}&centers=60&method=tfp&window=103", OCTET, BODY, 422, "limit of 101"),
    (f"height={H}&width={W}&centers=2a,3", OCTET, BODY, 422, "centers"),
    (f"height={H}&width={W}&centers=45&binning=2&method=tfp", OCTET, BODY, 422, "method net"),
    (f"height={H}&width={W}&centers=45&binning=2&quality=fast", OCTET, BODY, 422, "quality best"),
    (f"height={H}&width={W}&centers=45&binning=3", OCTET, BODY, 422, "window 123 is over"),
    (f"height={H}&width={W}&centers=45&binning=0", OCTET, BODY, 422, "binning"),
    (f"height={H}&width={W}&centers=30&binning=2", OCTET, BODY, 422, "first valid centre is 41"),
    (f"height={H}&width={W}&centers=20&colour=red", OCTET, BODY, 422, "colour"),
    (f"height=0&width={W}&centers=20", OCTET, BODY, 422, "height"),
    ("height=400&width=400&centers=20", OCTET, BODY, 422, "100000 pixels"),
    (f"height={H}&width={W}&centers=20", {"content-type": "image/png"}, BODY, 415, "Content-Type"),
    (f"height={H}&width={W}&centers=20", {}, BODY, 415, "Content-Type"),
    (f"height={H}&width={W}&centers=20", OCTET, b"", 422, "empty"),
    (f"height={H}&width={W}&centers=20", OCTET, NPY_BODY, 422, "the upload is a .npy file"),
    (f"height={H}&width={W}&centers=20", OCTET, BODY[:-1], 422, "whole number of 16x24 frames"),
    (f"height={H}&width={W}&centers=80", OCTET, BODY, 422, "no full 41-frame window"),
    (f"height={H}&width={W}&centers=19", OCTET, BODY, 422, "first valid centre is 20"),
    (f"height={H}&width={W}&stride=1", OCTET, BODY[: 40 * 48], 422, "shorter than the 41-frame"),
    ("height=250&width=400&centers=20", OCTET, bytes(241 * 12500), 413, "3000000 bytes"),
    ("height=16&width=16&centers=20", OCTET, bytes(2001 * 32), 413, "2000 frames"),
    ("height=16&width=16&stride=1&method=tfi&window=1", OCTET, bytes(100 * 32), 413, "TFI"),
]


@pytest.mark.parametrize(("query", "headers", "body", "status", "words"), BAD_REQUESTS)
def test_bad_requests_get_4xx_json(service, query, headers, body, status, words):
    response = post(service, query, body, headers)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and words in detail
    assert service.get("/healthz").status_code == 200


def test_unknown_paths_and_methods(service):
    assert httpx.get(f"{service.url}/v1/reconstruct").status_code == 405
    response = httpx.get(f"{service.url}/v2/nothing")
    assert response.status_code == 404 and response.json() == {"detail": "Not Found"}


def test_the_server_keeps_serving_after_errors(service, model):
    for query, headers, body, status, _ in BAD_REQUESTS:
        assert post(service, query, body, headers).status_code == status
    frames, done = parse_frames(post(service, f"height={H}&width={W}&centers=20").content)
    assert [f.center for f in frames] == [20] and done.frames == 1


def test_a_client_that_leaves_stops_the_work(service):
    spikes, body = stream_bytes(400, H, W, seed=3)
    before = _metric(service, 'spk2img_errors_total{kind="disconnect",status="disconnect"}')
    received = _metric(service, 'spk2img_spike_frames_received_total{method="tfp"}')
    client = DuplexClient(service.port)
    client.start(f"/v1/reconstruct?height={H}&width={W}&stride=1&method=tfp&window=41")
    client.send(body[: 100 * 48])
    assert client.read_head().status_code == 200
    assert client.read_some()  # frames are coming
    client.close()  # leave with 300 frames unsent
    deadline = time.monotonic() + 10
    while (
        _metric(service, "spk2img_admitted_requests")
        or _metric(service, 'spk2img_errors_total{kind="disconnect",status="disconnect"}') == before
    ):
        assert time.monotonic() < deadline, "the server did not notice the client left"
        time.sleep(0.05)
    decoded = _metric(service, 'spk2img_spike_frames_received_total{method="tfp"}') - received
    assert 41 <= decoded <= 100
    assert service.get("/healthz").status_code == 200


def test_metrics(service):
    post(service, f"height={H}&width={W}&centers=20,30&method=tfp&format=uint8")
    post(service, f"height={H}&width={W}&centers=20", headers={})
    text = service.get("/metrics").text
    for name in (
        "spk2img_http_requests_total",
        "spk2img_http_request_duration_seconds_bucket",
        "spk2img_spike_frames_received_total",
        "spk2img_frames_sent_total",
        "spk2img_errors_total",
        "spk2img_inference_queue_depth",
        "spk2img_admitted_requests",
    ):
        assert name in text
    assert _metric(service, 'spk2img_frames_sent_total{format="uint8",method="tfp"}') >= 2
    assert _metric(service, 'spk2img_errors_total{kind="http",status="415"}') >= 1
    assert _metric(service, "spk2img_inference_queue_depth") == 0


def test_in_band_error_counted(service):
    before = _metric(service, 'spk2img_errors_total{kind="in_band",status="422"}')
    response = post(service, f"height={H}&width={W}&centers=20,500", iter([BODY]))  # chunked
    frames, last = parse_frames(response.content)
    assert [f.center for f in frames] == [20] and isinstance(last, ErrorRecord)
    assert _metric(service, 'spk2img_errors_total{kind="in_band",status="422"}') == before + 1


def _metric(service, sample: str) -> float:
    """The value of one sample of ``/metrics`` (0 when absent)."""
    text = service.get("/metrics").text
    match = re.search(rf"^{re.escape(sample)} (\S+)$", text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0
