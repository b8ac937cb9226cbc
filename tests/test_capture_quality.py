"""Real-capture quality (spk2img.evaluation.capture_quality): the centres, the binned
networks' scale, and NIQE per frame and method."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from spk2img.evaluation.capture_quality import capture_centres, niqe_scores, reconstruct_at
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.windows import net_window


@given(frames=st.integers(1, 2000), binning=st.integers(1, 8), step=st.integers(1, 50))
def test_every_centre_holds_a_full_window_and_the_next_would_not(frames, binning, step):
    centers = capture_centres(frames, binning, step)
    half = net_window(41, binning) // 2
    assert all(k - half >= 0 and k + half < frames for k in centers)
    assert np.all(np.diff(centers) == step)
    if centers:
        assert centers[0] == half and centers[-1] + step + half >= frames
    else:
        assert frames < net_window(41, binning)


def _every_fourth_frame(frames: int, h: int = 3, w: int = 5) -> np.ndarray:
    """``(frames, h, w)`` 0/1: every pixel fires on frames 0, 4, 8, ... (0.25 spikes a frame)."""
    spikes = np.zeros((frames, h, w), np.uint8)
    spikes[::4] = 1
    return spikes


@pytest.mark.parametrize("binning", [1, 2, 4])
def test_a_binned_network_answers_on_the_streams_scale(binning):
    """The stand-in network returns its window's firing rate. Merging ``binning`` frames
    multiplies the rate by ``binning`` (0.25 -> 0.5 -> 1.0); the division brings it back."""
    spikes = _every_fourth_frame(net_window(41, binning) + 40)
    centers = capture_centres(len(spikes), binning, 10)
    seen = []

    def rate(window: np.ndarray) -> np.ndarray:
        seen.append(window.shape)
        return window.mean(axis=1)

    frames = reconstruct_at(spikes, centers, {"rate": rate}, binning)
    assert seen == [(1, 41, 3, 5)] * len(centers)
    assert frames["rate"].shape == (len(centers), 3, 5)
    # 41 merged frames hold 11, 21 or 41 spikes: the rate is within one frame of 0.25
    np.testing.assert_allclose(frames["rate"], 0.25, atol=1 / 41)
    np.testing.assert_array_equal(frames["TFP-41"], tfp(spikes, centers, 41))
    np.testing.assert_array_equal(frames["TFI"], tfi(spikes, centers, 41))


def test_niqe_is_scored_per_frame_and_noise_rates_worse(grey_photo):
    pytest.importorskip("skvideo")
    from spk2img.evaluation.niqe import display_grey, niqe, niqe_corners

    linear = (grey_photo[:250, :250] / 255) ** 2.2
    noise = np.random.default_rng(1).normal(0, 0.05, (2, 250, 250))
    frames = {"clean": np.stack([linear, linear.T]), "noisy": np.clip(linear + noise, 0, 1)}
    scores = niqe_scores(frames)
    assert scores["clean"]["niqe"] == [niqe(display_grey(f)) for f in frames["clean"]]
    assert scores["noisy"]["corners"] == [niqe_corners(display_grey(f)) for f in frames["noisy"]]
    assert min(scores["noisy"]["niqe"]) > max(scores["clean"]["niqe"])
