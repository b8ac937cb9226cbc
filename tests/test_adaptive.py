"""Compute that fits the scene (``quality``): the motion/brightness test finds what moves, the
balanced tier runs the network only there, and the tiers agree across CLI and service."""

import numpy as np
import pytest

from spk2img.cli import main
from spk2img.runtime.adaptive import (
    DIM_COUNT,
    MOTION_THRESHOLD,
    TILE,
    _tile_means,
    balanced_image,
    network_tiles,
    tile_statistics,
)
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, simulate

SENSORS = {"ideal": SensorConfig.ideal(), "real": SensorConfig.real()}


def _window(motion: str, brightness: str, sensor: str, seed: int, size=(64, 96)) -> np.ndarray:
    rng = np.random.default_rng([31337, seed])
    scene = random_scene(rng, *size, motion, brightness)
    return simulate(scene, 41, SENSORS[sensor], rng)


def _change(window: np.ndarray) -> np.ndarray:
    return tile_statistics(window)[0]


@pytest.mark.parametrize("brightness", ["dim", "normal", "bright"])
@pytest.mark.parametrize("sensor", ["ideal", "real"])
def test_static_scenes_never_count_as_moving(brightness, sensor):
    for seed in range(3):
        change = _change(_window("static", brightness, sensor, seed))
        assert change.max() <= MOTION_THRESHOLD


@pytest.mark.parametrize("sensor", ["ideal", "real"])
def test_fast_scenes_mostly_move(sensor):
    shares = [
        (_change(_window("fast", "normal", sensor, seed)) > MOTION_THRESHOLD).mean()
        for seed in range(4)
    ]
    assert np.mean(shares) > 0.5


def test_tile_means_cover_ragged_edges():
    image = np.arange(35 * 50, dtype=np.float32).reshape(35, 50)
    means = _tile_means(image)
    assert means.shape == (3, 4)
    assert means[-1, -1] == pytest.approx(image[32:, 48:].mean())
    assert means[0, 0] == pytest.approx(image[:TILE, :TILE].mean())


def _never(_windows):
    raise AssertionError("the network ran on a static, well-lit window")


def test_static_bright_window_is_tfp_without_the_network():
    window = _window("static", "bright", "real", 0)
    image, share = balanced_image(window, _never)
    assert share == 0.0
    np.testing.assert_allclose(image, np.clip(window.mean(0) / 0.6, 0, 1), atol=1e-6)


def test_dim_and_moving_windows_run_the_network_where_needed():
    calls = []

    def marker(windows):  # stands in for the network: 2.0 marks its pixels
        calls.append(windows.shape)
        return np.full((len(windows), *windows.shape[2:]), 2.0, np.float32)

    dim = _window("static", "dim", "ideal", 1)
    assert network_tiles(dim).all()  # every tile dim (under DIM_COUNT spikes in 40 frames)
    image, share = balanced_image(dim, marker)
    assert share == 1.0 and (image == 2.0).all() and calls[-1] == (1, 41, 64, 96)

    # a moving patch in a static, well-lit frame: the network runs on its tiles plus context
    window = _window("static", "bright", "ideal", 2, size=(96, 128))
    rng = np.random.default_rng(0)
    window[:, 48:64, 64:80] = rng.random((41, 16, 16)) < np.linspace(0.05, 0.9, 41)[:, None, None]
    tiles = network_tiles(window)
    assert tiles.sum() == 1 and tiles[48 // TILE, 64 // TILE]
    image, share = balanced_image(window, marker)
    assert calls[-1] == (1, 41, 16 + 32, 16 + 32)  # the tile and 16 pixels of context around
    assert (image[48:64, 64:80] == 2.0).all() and (image <= 1.0).sum() == 96 * 128 - 256
    assert share == pytest.approx(48 * 48 / (96 * 128))
    assert DIM_COUNT > 0


def test_cli_tiers(tmp_path, capsys):
    rng = np.random.default_rng(7)
    spikes = simulate(random_scene(rng, 40, 56, "static", "bright"), 90, SENSORS["real"], rng)
    source = tmp_path / "s.npy"
    np.save(source, spikes)
    out = {}
    variants = {
        "fast": ["--quality", "fast"],
        "tfp": ["--method", "tfp"],
        "balanced": ["--quality", "balanced"],
    }
    for name, extra in variants.items():
        out[name] = tmp_path / f"{name}.npz"
        args = ["reconstruct", str(source), "--out", str(out[name]), "--stride", "9"]
        assert main([*args, "--no-progress", *extra]) == 0
    frames = {k: np.load(v)["frames"] for k, v in out.items()}
    np.testing.assert_array_equal(frames["fast"], frames["tfp"])  # TFP-41
    np.testing.assert_array_equal(frames["balanced"], frames["tfp"])  # static and bright
    bad = ["reconstruct", str(source), "--out", str(tmp_path / "x.npz"), "--method", "tfi"]
    assert main([*bad, "--quality", "balanced"]) == 2
    assert "quality is for method net" in capsys.readouterr().err
