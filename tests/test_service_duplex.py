"""Full duplex over a raw socket (h11): frames come back while the upload is still going on, the
result does not depend on how the upload is split, and late errors arrive in-band."""

from __future__ import annotations

import httpx
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from service_support import OCTET, DuplexClient, parse_frames, post_chunks, stream_bytes

from spk2img.protocol.framing import DoneRecord, ErrorRecord, FrameRecord, RecordParser


def test_first_frame_arrives_before_the_upload_ends(service):
    """A 250x400 stream of 161 frames (docs/http.md's case): send 70 frames, read a frame, send the
    rest. The frames received during the upload equal the start of the whole answer."""
    height, width, total, first_part = 250, 400, 161, 70
    _, body = stream_bytes(total, height, width, seed=5)
    target = f"/v1/reconstruct?height={height}&width={width}&stride=10&method=net"
    whole = httpx.post(service.url + target, content=body, headers=OCTET, timeout=60).content

    client = DuplexClient(service.port)
    try:
        client.start(target, length=len(body))
        client.send(body[: first_part * 12500])
        assert client.read_head().status_code == 200
        parser, early, early_frames = RecordParser(), bytearray(), []
        while not early_frames:  # read until one whole frame has come back
            piece = client.read_some()
            assert piece, "the response ended before the upload"
            early += piece
            early_frames = [r for r in parser.feed(piece) if isinstance(r, FrameRecord)]
        sender = client.send_in_background(body[first_part * 12500 :])
        rest = client.read_all()
        sender.join(10)
    finally:
        client.close()
    assert early_frames[0].center == 20 and len(early) >= 400_000  # one 250x400 float32 frame
    print(f"\nduplex: {len(early)} response bytes after {first_part} of {total} frames uploaded")
    assert bytes(early) + rest == whole
    frames, done = parse_frames(whole)
    assert isinstance(done, DoneRecord) and [f.center for f in frames] == list(range(20, 141, 10))


H, W, T = 16, 24, 70
_, SMALL = stream_bytes(T, H, W, seed=7)
TARGETS = [
    f"/v1/reconstruct?height={H}&width={W}&stride=3&method=net",
    f"/v1/reconstruct?height={H}&width={W}&stride=2&method=tfp&window=7&format=uint8",
    f"/v1/reconstruct?height={H}&width={W}&centers=20,33,49&method=tfi",
]


@settings(max_examples=24, deadline=None)
@given(
    which=st.integers(0, len(TARGETS) - 1),
    cuts=st.lists(st.integers(0, len(SMALL)), max_size=6),
)
def test_any_split_of_the_upload_gives_the_same_bytes(service, which, cuts):
    target = TARGETS[which]
    whole = httpx.post(service.url + target, content=SMALL, headers=OCTET, timeout=30)
    bounds = [0, *sorted(cuts), len(SMALL)]
    chunks = [SMALL[a:b] for a, b in zip(bounds, bounds[1:], strict=False)]
    status, _, body = post_chunks(service.port, target, chunks, pause=0.002)
    assert status == whole.status_code == 200
    assert body == whole.content


def test_upload_ending_mid_frame_after_frames_is_an_in_band_error(service):
    target = f"/v1/reconstruct?height={H}&width={W}&stride=5&method=tfp"
    status, headers, body = post_chunks(service.port, target, [SMALL[: 60 * 48], b"\x01" * 17])
    assert status == 200 and headers[b"content-type"] == b"application/x-spk2img-frames"
    frames, last = parse_frames(body)
    assert [f.center for f in frames] == list(range(20, 40, 5))
    assert isinstance(last, ErrorRecord) and last.status == 422
    assert "stream ended inside frame 60: 17 of 48 bytes" in last.detail


def test_chunked_errors_before_the_first_frame_are_json(service):
    target = f"/v1/reconstruct?height={H}&width={W}&centers=60"
    status, _, body = post_chunks(service.port, target, [SMALL[: 30 * 48], b"\x01" * 5])
    assert status == 422 and b"stream ended inside frame 30" in body
    status, _, body = post_chunks(service.port, target, [])
    assert status == 422 and b"empty spike stream" in body
    status, _, body = post_chunks(service.port, target, [SMALL[: 50 * 48]])
    assert status == 422 and b"no full 41-frame window" in body


def test_limit_crossed_mid_stream_is_an_in_band_413(service):
    """Frames out, then the upload crosses the frame limit: the stream ends with an ``ERRO``
    413 after the frames (the server reads and drops the rest of the body still coming)."""
    _, long = stream_bytes(6000, 4, 4, seed=2)  # 2 bytes a frame; the limit is 2000 frames
    target = "/v1/reconstruct?height=4&width=4&stride=50&method=tfp"
    client = DuplexClient(service.port)
    try:
        client.start(target)
        client.send(long[:200])  # 100 frames: the first frame's window is in
        assert client.read_head().status_code == 200
        first = client.read_some()  # a whole piece has come back before the rest is sent
        sender = client.send_in_background(long[200:])
        body = first + client.read_all()
        sender.join(30)
    finally:
        client.close()
    frames, last = parse_frames(body)
    centers = [f.center for f in frames]
    assert centers == list(range(20, 50 * len(frames), 50))  # at least the first: 20
    assert isinstance(last, ErrorRecord) and last.status == 413 and "2000 frames" in last.detail


def test_frames_equal_a_content_length_upload(service):
    """The same stream chunked and with Content-Length: same frames, same DONE."""
    target = f"/v1/reconstruct?height={H}&width={W}&stride=4&method=net&format=png"
    status, _, chunked = post_chunks(service.port, target, [SMALL[:1000], SMALL[1000:]])
    whole = httpx.post(service.url + target, content=SMALL, headers=OCTET, timeout=30)
    assert status == 200 and chunked == whole.content
    frames, done = parse_frames(chunked)
    assert done.frames == len(frames) and all(f.image.dtype == np.uint8 for f in frames)
