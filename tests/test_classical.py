import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import encode_dat, tfi_reference, tfp_reference

from spk2img.cli import main
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.stream import TFIStream, TFPStream, collect
from spk2img.runtime.windows import CenterPlan, WindowError


def _stream(t=120, h=13, w=21, seed=0):
    rng = np.random.default_rng(seed)
    rate = rng.random((h, w)) * 0.6  # a different firing rate per pixel, some nearly dark
    return (rng.random((t, h, w)) < rate).astype(np.uint8)


@pytest.mark.parametrize("method", ["tfp", "tfi"])
def test_cli_agrees_with_independent_implementation(tmp_path, method):
    frames = _stream()
    path = tmp_path / "in.dat"
    path.write_bytes(encode_dat(frames))  # written by the independent encoder
    out = tmp_path / "out.npz"
    code = main(
        [
            "reconstruct",
            str(path),
            "--out",
            str(out),
            "--height",
            "13",
            "--width",
            "21",
            "--method",
            method,
            "--window",
            "41",
            "--centers",
            "20,57,99",
            "--no-progress",
        ]
    )
    assert code == 0
    got = np.load(out)
    assert got["frames"].dtype == np.float32 and got["centers"].dtype == np.int64
    np.testing.assert_array_equal(got["centers"], [20, 57, 99])
    for k, image in zip(got["centers"], got["frames"], strict=True):
        ref = tfp_reference(frames, k, 41) if method == "tfp" else tfi_reference(frames, k)
        np.testing.assert_allclose(image, ref, atol=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_streaming_is_identical_for_every_chunking(data):
    frames = _stream(t=60, h=5, w=6, seed=data.draw(st.integers(0, 1000)))
    cuts = sorted(data.draw(st.lists(st.integers(0, 60), max_size=6)))
    chunks = [frames[a:b] for a, b in zip([0, *cuts], [*cuts, 60], strict=True)]
    for cls, window in [(TFPStream, 9), (TFIStream, 9)]:
        recon = cls(5, 6, CenterPlan(window, stride=3))
        pieces = [r for c in chunks for r in recon.push(c)] + recon.close()
        images, centers = collect(pieces, 5, 6)
        ref = (tfp if cls is TFPStream else tfi)(frames, centers, window)
        np.testing.assert_array_equal(images, ref)
        np.testing.assert_array_equal(centers, np.arange(4, 56, 3))


def test_sliding_tfp_matches_direct_mean_over_long_stream():
    frames = _stream(t=400, h=4, w=5, seed=3)
    centers = np.arange(20, 380)
    got = tfp(frames, centers, 41)
    ref = np.stack([tfp_reference(frames, k, 41) for k in centers])
    np.testing.assert_allclose(got, ref, atol=1e-6)


@pytest.mark.parametrize("fill", [0, 1])
def test_extremes_are_finite_and_in_range(fill):
    frames = np.full((50, 6, 7), fill, np.uint8)
    for image in (tfp(frames, [25], 41), tfi(frames, [25])):
        assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
        if fill:
            np.testing.assert_allclose(image, 1.0)
    # no spike at all: TFP is 0; TFI's interval is bounded by the stream's edges
    # (t_prev = -1, t_next = T = 50), so 1 / (0.6 * 51): finite and dark
    if not fill:
        np.testing.assert_allclose(tfp(frames, [25], 41), 0)
        np.testing.assert_allclose(tfi(frames, [25]), 1 / (0.6 * 51), rtol=1e-6)


def test_single_spike_tfi():
    frames = np.zeros((30, 1, 1), np.uint8)
    frames[10] = 1
    # k = 15: t_prev = 10, no spike after -> t_next = T = 30
    np.testing.assert_allclose(tfi(frames, [15]), 1 / (0.6 * 20), rtol=1e-6)


def test_window_errors():
    frames = _stream(t=50)
    with pytest.raises(WindowError, match="no full 41-frame window"):
        tfp(frames, [30], 41)
    with pytest.raises(WindowError, match="shorter than"):
        tfp(frames[:30], [20], 41)
    with pytest.raises(WindowError, match="odd"):
        tfp(frames, [25], 10)
    with pytest.raises(WindowError, match="comma-separated"):
        CenterPlan.parse(41, "4,x")
