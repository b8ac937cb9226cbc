"""Fitting a sensor preset to a capture: the estimators recover simulated sensors, the CLI
writes a preset the simulator loads, and the shipped preset is the real capture's."""

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from spk2img.cli import main
from spk2img.sim.scenes import StillScene
from spk2img.sim.sensor_fit import FITTED_PRESET, fit_sensor, load_preset
from spk2img.sim.simulator import SensorConfig, SpikeSimulator

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
REAL_CAPTURE = REAL / "uhsr_helicopter_250x250.npz"


def still_camera(sensor: SensorConfig, seed: int = 0) -> SpikeSimulator:
    """``sensor`` filming a smooth, dim still scene (like the real capture), 160x160."""
    y, x = np.mgrid[0:160, 0:160] / 160
    image = 0.03 + 0.05 * (0.5 + 0.5 * np.sin(6 * x) * np.cos(4 * y))
    return SpikeSimulator(StillScene(image.astype(np.float32)), sensor, np.random.default_rng(seed))


def still_capture(sensor: SensorConfig, seed: int = 0) -> np.ndarray:
    """200 frames of :func:`still_camera`."""
    return still_camera(sensor, seed).run(200)


@pytest.mark.parametrize("photons, mismatch", [(30.0, 0.0), (300.0, 0.03)])
def test_shot_noise_and_mismatch_are_recovered(photons, mismatch):
    true = SensorConfig(shot_noise=True, photons_per_threshold=photons, threshold_mismatch=mismatch)
    fitted, report = fit_sensor(still_capture(true))
    assert fitted.photons_per_threshold == pytest.approx(photons, rel=0.15)
    assert fitted.threshold_mismatch == pytest.approx(mismatch, abs=0.01)
    assert fitted.hot_pixel_fraction == 0 and report["isi_pixels"] > 10_000


def test_hot_pixels_are_recovered_and_an_ideal_sensor_is_found_quiet():
    camera = still_camera(SensorConfig(hot_pixel_fraction=1e-3, hot_pixel_rate=0.4), seed=1)
    drawn = float((camera.dark > 0).mean())  # the hot pixels this sensor drew
    fitted, _ = fit_sensor(camera.run(200))
    assert fitted.hot_pixel_fraction == pytest.approx(drawn, rel=0.1)
    assert fitted.hot_pixel_rate == pytest.approx(0.4, abs=0.05)
    assert fitted.photons_per_threshold > 1000 and fitted.threshold_mismatch < 0.01


def test_the_dark_current_is_bounded_by_the_darkest_pixels():
    fitted, report = fit_sensor(still_capture(SensorConfig(dark_current=0.004), seed=2))
    darkest_rate = 0.6 * 0.03 + 0.004
    assert fitted.dark_current <= report["dark_current_upper_bound"] <= 1.2 * darkest_rate
    assert fitted.dark_current == pytest.approx(report["dark_current_upper_bound"] / 2)


def test_fit_sensor_cli_writes_a_preset_the_simulator_loads(tmp_path, capsys):
    capture = tmp_path / "still.npy"
    np.save(capture, still_capture(SensorConfig.real(), seed=3))
    preset = tmp_path / "preset.json"
    assert main(["fit-sensor", str(capture), "--out", str(preset)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert asdict(load_preset(preset)) == printed["sensor"]
    out = tmp_path / "sim.dat"
    size = "--frames 8 --height 8 --width 8 --sensor fitted --no-progress".split()
    assert main(["simulate", str(out), *size]) == 0
    assert out.stat().st_size == 8 * 8


def test_fit_sensor_rejects_bad_input(tmp_path, capsys):
    short = tmp_path / "short.npy"
    np.save(short, np.zeros((5, 8, 8), np.uint8))
    assert main(["fit-sensor", str(short)]) == 2
    assert main(["fit-sensor", str(tmp_path / "missing.npz")]) == 2
    dark = tmp_path / "dark.npy"  # long enough, but one spike in all: nothing to fit
    spikes = np.zeros((50, 8, 8), np.uint8)
    spikes[10, 3, 3] = 1
    np.save(dark, spikes)
    assert main(["fit-sensor", str(dark)]) == 2
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="not a sensor preset"):
        load_preset(tmp_path / "bad.json")
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "only 0 pixels (hot ones aside) fire" in err[-1]


@pytest.mark.skipif(not REAL_CAPTURE.is_file(), reason="the real capture is not beside the repo")
def test_the_shipped_preset_is_the_fit_of_the_real_capture():
    with np.load(REAL_CAPTURE) as z:
        fitted, _ = fit_sensor(z["spk"])
    assert asdict(fitted) == pytest.approx(asdict(load_preset(FITTED_PRESET)))
    assert 20 < fitted.photons_per_threshold < 1000 and fitted.threshold_mismatch < 0.2
