"""Binning for dim streams: K stream frames merged into each of the network's 41 frames
(spk2img.runtime.stream.bin_frames, NetStream, suggest_binning), through the API and the CLI; and
the shipped model with it on a dim simulated scene against ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import tfp_reference

import spk2img
from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.evaluation.metrics import psnr
from spk2img.runtime.binning import suggest_binning
from spk2img.runtime.methods import build_reconstructor, method_plan
from spk2img.runtime.stream import NetStream, bin_frames, collect, frame_chunks, run_stream
from spk2img.runtime.windows import MAX_BINNING, WindowError, net_window
from spk2img.sim.scenes import StillScene, dead_leaves
from spk2img.sim.simulator import SensorConfig, simulate

H, W = 12, 16


def tfp41(windows: np.ndarray) -> np.ndarray:
    """A stand-in network: TFP over its 41 frames, ``(B, 41, H, W)`` -> ``(B, H, W)``."""
    return np.clip(windows.mean(axis=1) / 0.6, 0.0, 1.0).astype(np.float32)


def bernoulli(frames: int, rate: float | np.ndarray, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.random((frames, H, W)) < rate).astype(np.uint8)


@settings(max_examples=40, deadline=None)
@given(binning=st.integers(1, 6), seed=st.integers(0, 2**31 - 1))
def test_a_binned_frame_is_the_union_of_its_stream_frames(binning, seed):
    window = bernoulli(net_window(41, binning), 0.2, seed)
    merged = bin_frames(window, binning)
    assert merged.shape == (41, H, W)
    for j in range(41):
        fired = window[j * binning : (j + 1) * binning].any(axis=0)
        np.testing.assert_array_equal(merged[j], fired)


@pytest.mark.parametrize("binning", [1, 2, 3, 4])
def test_window_length_stays_odd_and_centred(binning):
    window = net_window(41, binning)
    assert window % 2 == 1 and window - 41 * binning in (0, 1)
    plan = method_plan("net", None, 5, binning=binning)
    assert plan.window == window and plan.half == window // 2


@pytest.mark.parametrize("binning", [2, 3, 5])
def test_net_stream_runs_the_network_on_merged_windows(binning):
    spikes = bernoulli(400, np.linspace(0.01, 0.08, W), seed=binning)
    plan = method_plan("net", None, 17, binning=binning)
    recon = build_reconstructor("net", H, W, plan, tfp41, max_batch=2, binning=binning)
    assert isinstance(recon, NetStream)
    frames, centers = collect(run_stream(recon, frame_chunks(spikes, 9)), H, W)
    half = net_window(41, binning) // 2
    assert centers.tolist() == list(range(half, 400 - half, 17))
    for k, image in zip(centers, frames, strict=True):
        window = spikes[k - half : k + half + 1]
        expected = tfp_reference(bin_frames(window, binning), 20, 41) / binning
        np.testing.assert_allclose(image, expected, atol=1e-6)


def test_binning_is_refused_where_it_does_not_apply():
    plan = method_plan("net", None, 7, binning=2)
    with pytest.raises(InputError, match="quality best"):
        build_reconstructor("net", H, W, plan, tfp41, quality="balanced", binning=2)
    with pytest.raises(InputError, match="method net"):
        method_plan("tfp", None, 7, binning=2)
    for bad in (0, MAX_BINNING + 1, 1.5):
        with pytest.raises(WindowError, match="binning"):
            net_window(41, bad)
    with pytest.raises(WindowError, match="83-frame window"):
        method_plan("net", "40", None, binning=2).centers_for(100)


@pytest.mark.parametrize(
    ("frames", "rate", "expected"),
    [
        (400, 0.3, 1),  # normally lit: no binning
        (400, 0.031, 3),  # the real capture's rate: 0.1 / 0.031
        (400, 0.012, 8),
        (100, 0.012, 2),  # a short stream: one window of 41 x 2 frames at most
    ],
)
def test_suggested_binning_follows_the_firing_rate(frames, rate, expected):
    assert suggest_binning(bernoulli(frames, rate, seed=7)) == expected


def test_suggested_binning_keeps_highlights_below_saturation():
    rate = np.full((H, W), 0.005)
    rate[0] = 0.25  # the mean rate (0.025) asks for 3; a row firing 0.25 a frame saturates at 3
    assert suggest_binning(bernoulli(400, rate, seed=3)) == 2


@pytest.fixture(scope="module")
def dim_still_scene():
    """A still dead-leaves scene at 0.03 spikes/pixel/frame (the real capture's light), filmed
    noise-free for 205 frames, and its truth."""
    rng = np.random.default_rng(11)
    image = dead_leaves(rng, 64, 64)
    image = np.clip(image * (0.05 / image.mean()), 0.0, 1.0).astype(np.float32)
    spikes = simulate(StillScene(image), 205, SensorConfig.ideal(), np.random.default_rng(12))
    return spikes, image


def test_shipped_model_gains_from_binning_on_a_dim_scene(dim_still_scene):
    spikes, truth = dim_still_scene
    recon = spk2img.Reconstructor("net", threads=1)
    plain = recon.reconstruct(spikes, centers=[102]).frames[0]
    auto = suggest_binning(spikes)
    binned = spk2img.Reconstructor("net", threads=1, binning=auto)
    merged = binned.reconstruct(spikes, centers=[102]).frames[0]
    scale = float(truth.max())
    assert auto == 3
    assert psnr(merged, truth, scale) > psnr(plain, truth, scale) + 3.0
    assert abs(float(merged.mean()) - float(truth.mean())) < 0.1 * float(truth.mean())


def test_cli_binning_auto_and_the_dim_stream_note(tmp_path, capsys, dim_still_scene):
    spikes, _ = dim_still_scene
    path = tmp_path / "dim.npy"
    np.save(path, spikes)
    out = tmp_path / "out.npz"
    args = ["reconstruct", str(path), "--out", str(out), "--centers", "102", "--no-progress"]
    assert main([*args, "--method", "tfp"]) == 0
    assert "--binning" not in capsys.readouterr().err  # only the network is told
    assert main(args) == 0
    assert "--binning 3 (or auto)" in capsys.readouterr().err
    assert main([*args, "--binning", "auto"]) == 0
    err = capsys.readouterr().err
    assert "binning 3 (0.03" in err and "123-frame windows" in err
    with np.load(out) as saved:
        expected = spk2img.reconstruct(spikes, centers=[102], binning=3).frames
        np.testing.assert_array_equal(saved["frames"], expected)


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--binning", "2", "--method", "tfp"], "binning is for method net"),
        (["--binning", "2", "--quality", "balanced"], "binning is for quality best"),
        (["--binning", "6"], "no full 247-frame window"),
    ],
)
def test_cli_binning_errors_exit_2(tmp_path, capsys, dim_still_scene, extra, words):
    path = tmp_path / "dim.npy"
    np.save(path, dim_still_scene[0])
    args = ["reconstruct", str(path), "--out", str(tmp_path / "o.npz"), "--centers", "102"]
    assert main([*args, "--no-progress", *extra]) == 2
    assert words in capsys.readouterr().err
