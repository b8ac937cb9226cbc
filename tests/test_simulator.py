"""Numerical checks of the spike-camera simulator (docs/format.md) and its scenes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.cli import main
from spk2img.io.light import SPIKE_RATE
from spk2img.io.spikes import frame_nbytes, unpack_frames
from spk2img.sim.scenes import (
    BRIGHTNESSES,
    MEAN_RANGES,
    MOTIONS,
    Motion,
    MovingImage,
    StillScene,
    random_scene,
    sample_bilinear,
)
from spk2img.sim.simulator import (
    GT_FRAMES,
    SensorConfig,
    SpikeSimulator,
    filmed_sample,
    ground_truth,
    simulate,
    training_sample,
)

# --- integrate-and-fire: the rate is 0.6·I ----------------------------------------------------


@pytest.mark.parametrize("level", [0.0, 0.01, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0])
def test_ideal_rate_is_0_6_times_intensity(level):
    spikes = simulate(StillScene.uniform(32, 32, level), 2000, rng=np.random.default_rng(1))
    assert spikes.dtype == np.uint8 and spikes.shape == (2000, 32, 32) and spikes.max() <= 1
    p = SPIKE_RATE * level
    binomial_se = np.sqrt(max(p * (1 - p), 1e-6) / spikes.size)
    assert abs(spikes.mean() - p) < 4 * binomial_se + 1e-6


@settings(max_examples=25, deadline=None)
@given(level=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1), frames=st.integers(1, 300))
def test_ideal_counts_are_within_one_spike_of_the_charge(level, seed, frames):
    # noise-free integrate-and-fire: a pixel's count is floor(q0 + 0.6·I·T), q0 in [0, 1)
    spikes = simulate(StillScene.uniform(8, 8, level), frames, rng=np.random.default_rng(seed))
    counts = spikes.sum(0, dtype=np.int64)
    assert np.all(np.abs(counts - SPIKE_RATE * level * frames) <= 1 + 1e-4)


def test_initial_charge_is_uniform_below_threshold():
    sim = SpikeSimulator(StillScene.uniform(64, 64, 0.5), rng=np.random.default_rng(2))
    assert 0 <= sim.charge.min() and sim.charge.max() < 1.0
    assert abs(sim.charge.mean() - 0.5) < 0.02
    # so the first spike comes at frame ceil((1 - q0) / 0.3) - 1: 1.2 on average
    first = np.argmax(sim.run(10), axis=0)
    assert abs(first.mean() - 1.2) < 0.1


def test_at_most_one_spike_a_frame_and_the_charge_is_clamped():
    sensor = SensorConfig(hot_pixel_fraction=1.0, hot_pixel_rate=0.9)  # 0.6 + 0.9 > 1 a frame
    sim = SpikeSimulator(StillScene.uniform(8, 8, 1.0), sensor, np.random.default_rng(3))
    spikes = sim.run(200)
    assert spikes[1:].min() == 1 and spikes.max() == 1  # saturated: fires every frame
    assert sim.charge.max() <= sim.threshold.max()  # overflow kept, never runs away


# --- each sensor noise changes its statistic and nothing else ---------------------------------


def _sensor_statistics(sensor: SensorConfig, seed: int = 4) -> dict[str, float]:
    """Statistics of 2000 frames of a 32x64 field, left half dark (I=0), right half I=0.47
    (0.282 spikes/frame: 28.2 in a 100-frame window, so counts round both ways)."""
    image = np.zeros((32, 64), np.float32)
    image[:, 32:] = 0.47
    spikes = simulate(StillScene(image), 2000, sensor, np.random.default_rng(seed))
    dark, lit = spikes[:, :, :32], spikes[:, :, 32:]
    rates = lit.mean(0)  # long-run rate of each lit pixel
    windows = lit.reshape(20, 100, 32, 32).sum(1, dtype=np.int64)  # counts in 100-frame windows
    return {
        "rate": float(np.median(rates)),
        "dark_rate": float(np.median(dark.mean(0))),
        "window_var": float(np.median(windows.var(0))),
        "rate_spread": float(1.4826 * np.median(np.abs(rates - np.median(rates)))),  # robust std
        "hot": int((dark.mean(0) > 0.1).sum()),
    }


TOLERANCE = {"rate": 0.004, "dark_rate": 5e-4, "window_var": 0.15, "rate_spread": 0.003}
REAL = SensorConfig.real()


@pytest.fixture(scope="module")
def ideal() -> dict[str, float]:
    return _sensor_statistics(SensorConfig.ideal())


def _changed(stats: dict[str, float], ideal: dict[str, float]) -> set[str]:
    changed = {k for k, tol in TOLERANCE.items() if abs(stats[k] - ideal[k]) > tol}
    return changed | ({"hot"} if stats["hot"] != ideal["hot"] else set())


def test_ideal_statistics(ideal):
    assert abs(ideal["rate"] - 0.282) < 0.001 and ideal["dark_rate"] == 0
    assert ideal["window_var"] <= 0.25 and ideal["rate_spread"] < 0.001 and ideal["hot"] == 0


def test_shot_noise_raises_short_window_variance_only(ideal):
    stats = _sensor_statistics(SensorConfig(shot_noise=True))
    # Poisson charge: variance 0.282 x 100 / 50 = 0.56 spikes^2 a window, on top of rounding
    assert stats["window_var"] > ideal["window_var"] + 0.4
    assert _changed(stats, ideal) == {"window_var"}


def test_dark_current_raises_the_rate_at_zero_intensity(ideal):
    stats = _sensor_statistics(SensorConfig(dark_current=REAL.dark_current))
    assert abs(stats["dark_rate"] - REAL.dark_current) < 3e-4
    assert _changed(stats, ideal) == {"dark_rate"}


def test_threshold_mismatch_spreads_the_long_run_rates(ideal):
    stats = _sensor_statistics(SensorConfig(threshold_mismatch=REAL.threshold_mismatch))
    # rate = 0.282 / (1 + 0.03 e): its spread across pixels is about 0.282 x 0.03 = 0.0085
    assert 0.006 < stats["rate_spread"] < 0.012
    assert _changed(stats, ideal) == {"rate_spread"}


def test_hot_pixels_are_a_few_pixels_with_a_high_rate(ideal):
    sensor = SensorConfig(hot_pixel_fraction=0.01, hot_pixel_rate=REAL.hot_pixel_rate)
    stats = _sensor_statistics(sensor)
    assert 3 <= stats["hot"] <= 25  # ~10 expected among the 1024 dark pixels
    assert _changed(stats, ideal) == {"hot"}
    rates = simulate(StillScene.uniform(32, 32, 0.0), 400, sensor, np.random.default_rng(5)).mean(0)
    assert np.all(np.abs(rates[rates > 0.1] - REAL.hot_pixel_rate) < 0.01)


def test_real_preset_keeps_the_light_convention(ideal):
    stats = _sensor_statistics(REAL)
    assert abs(stats["rate"] - 0.282) < 0.01  # the noises perturb; the mean stays 0.6·I
    assert _changed(stats, ideal) >= {"window_var", "dark_rate", "rate_spread"}


# --- seeding -----------------------------------------------------------------------------------


@pytest.mark.parametrize("sensor", [SensorConfig.ideal(), SensorConfig.real()])
def test_same_seed_same_stream(sensor):
    def run(seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        return simulate(random_scene(rng, 24, 40, motion="fast"), 60, sensor, rng)

    assert np.array_equal(run(7), run(7))
    assert not np.array_equal(run(7), run(8))


def test_training_sample_is_seeded_and_shaped():
    spikes, gt = training_sample(np.random.default_rng(9), 40, 48)
    again = training_sample(np.random.default_rng(9), 40, 48)
    assert np.array_equal(spikes, again[0]) and np.array_equal(gt, again[1])
    assert spikes.shape == (41, 40, 48) and spikes.dtype == np.uint8 and spikes.max() <= 1
    assert gt.shape == (5, 40, 48) and gt.dtype == np.float32
    assert GT_FRAMES == (6, 13, 20, 27, 34)


def test_training_sample_gt_is_the_scene_at_the_block_centres():
    # same draws: the scene and sensor of a training sample, rebuilt from the same seed
    spikes, gt = training_sample(np.random.default_rng(10), 32, 32, SensorConfig.ideal())
    rng = np.random.default_rng(10)
    scene = random_scene(rng, 32, 32)
    assert np.array_equal(gt, np.stack([scene.intensity(k + 0.5) for k in GT_FRAMES]))
    assert np.array_equal(spikes, simulate(scene, 41, SensorConfig.ideal(), rng))


def test_filmed_sample_is_the_training_sample_and_names_its_sensor():
    # the validation and test sets use filmed_sample: the same draws as training_sample
    for seed in range(6):
        spikes, gt = training_sample(np.random.default_rng(seed), 24, 32)
        again, gt_again, sensor = filmed_sample(np.random.default_rng(seed), 24, 32)
        assert np.array_equal(spikes, again) and np.array_equal(gt, gt_again)
        rng = np.random.default_rng(seed)
        random_scene(rng, 24, 32)
        assert sensor == SensorConfig.random(rng)
    kinds = {filmed_sample(np.random.default_rng(s), 8, 8)[2].shot_noise for s in range(12)}
    assert kinds == {True, False}  # both regimes are drawn


# --- scenes: motion, brightness, ground truth --------------------------------------------------


def _track_one_frame(motion: Motion, y0: np.ndarray, x0: np.ndarray, t: float):
    """Where the content at output pixels ``(y0, x0)`` at time ``t`` is at ``t + 1``: solve
    ``p(y, x, t + 1) = p(y0, x0, t)`` by Newton's method (Jacobian by central differences)."""

    def coords(y: np.ndarray, x: np.ndarray, time: float) -> np.ndarray:
        return np.stack([c[0] for c in motion.source_coords(y, x, [time])])  # (2, *S)

    target, y, x = coords(y0, x0, t), y0.copy(), x0.copy()
    for _ in range(8):
        r = target - coords(y, x, t + 1)
        jy = coords(y + 0.5, x, t + 1) - coords(y - 0.5, x, t + 1)  # d(py, px)/dy
        jx = coords(y, x + 0.5, t + 1) - coords(y, x - 0.5, t + 1)  # d(py, px)/dx
        det = jy[0] * jx[1] - jx[0] * jy[1]
        y, x = y + (jx[1] * r[0] - jx[0] * r[1]) / det, x + (jy[0] * r[1] - jy[1] * r[0]) / det
    return y, x


@pytest.mark.parametrize("speed", [0.1, 0.5, 1.5, 3.0])
def test_motion_moves_content_at_the_requested_speed(speed):
    motion = Motion(np.random.default_rng(11), 48, 64, speed)
    assert abs(motion.mean_speed() - speed) < 0.02 * speed
    y0, x0 = (a.astype(float) for a in np.mgrid[4:48:8, 4:64:8])
    moved = [
        np.hypot(*np.subtract(_track_one_frame(motion, y0, x0, t), (y0, x0)))
        for t in np.linspace(0, 60, 7)
    ]
    assert abs(np.mean(moved) - speed) < 0.15 * speed


@pytest.mark.parametrize("speed", [0.25, 1.0, 2.5])
def test_panning_ground_truth_shifts_by_speed_per_frame(speed):
    rng = np.random.default_rng(12)
    motion = Motion(rng, 48, 48, speed, mix=(1.0, 0.0, 0.0, 0.0))
    motion.angle0, motion.log_scale0 = 0.0, 0.0  # upright, one source px per output px
    motion.clock *= speed / motion.mean_speed()
    noise = np.random.default_rng(13).uniform(size=(90, 90)).astype(np.float32)
    source = (noise + np.roll(noise, 1, 0) + np.roll(noise, 1, 1)) / 3  # a little smoothness
    scene = MovingImage(source, 48, 48, motion, {})
    lag = max(1, round(6 / speed))  # about 6 px of motion
    a, b = ground_truth(scene, [10, 10 + lag])
    # the integer shift of b against a with the least squared difference
    shifts = range(-12, 13)
    ssd = np.array(
        [
            [
                np.mean((b[14:34, 14:34] - a[14 + dy : 34 + dy, 14 + dx : 34 + dx]) ** 2)
                for dx in shifts
            ]
            for dy in shifts
        ]
    )
    iy, ix = np.unravel_index(np.argmin(ssd), ssd.shape)
    shift = np.hypot(shifts[iy], shifts[ix])
    assert abs(shift / lag - speed) < 0.2 * speed + 0.75 / lag


def test_static_scenes_do_not_change_and_moving_ones_do():
    rng = np.random.default_rng(14)
    change = {}
    for motion in MOTIONS:
        scene = random_scene(rng, 32, 48, motion=motion, brightness="normal")
        gt = ground_truth(scene, range(0, 41))
        change[motion] = float(np.abs(np.diff(gt, axis=0)).mean() / gt.mean())
    assert change["static"] == 0
    assert 0 < change["slow"] < change["fast"]


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    motion=st.sampled_from(MOTIONS),
    brightness=st.sampled_from(BRIGHTNESSES),
)
def test_ground_truth_is_linear_intensity_in_range(seed, motion, brightness):
    scene = random_scene(np.random.default_rng(seed), 20, 28, motion, brightness)
    gt = ground_truth(scene, [0, 20, 300])
    assert gt.dtype == np.float32 and gt.shape == (3, 20, 28)
    assert gt.min() >= 0 and gt.max() <= 1 and np.isfinite(gt).all()
    lo, hi = MEAN_RANGES[brightness]
    assert lo - 1e-3 <= scene.source.mean() <= hi + 1e-3
    assert scene.meta["motion"] == motion and scene.meta["brightness"] == brightness
    json.dumps(scene.meta)


def test_bilinear_sampling_interpolates_and_mirrors():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    y = np.array([0, 1, 0.5, 2, -1, 3, 0], np.float32)
    x = np.array([0, 2, 0.5, 3, 0, 0, -2.5], np.float32)
    # (-1, 0) mirrors to (1, 0); (3, 0) to (1, 0); (0, -2.5) to (0, 2.5)
    assert np.allclose(sample_bilinear(image, y, x), [0, 6, 2.5, 11, 4, 4, 2.5])


# --- the simulate command ----------------------------------------------------------------------


def test_simulate_cli_writes_a_dat_that_round_trips(tmp_path):
    out = tmp_path / "s.dat"
    args = ["simulate", str(out), "--frames", "70", "--height", "13", "--width", "21"]
    assert main([*args, "--seed", "3", "--motion", "slow", "--no-progress"]) == 0
    data = out.read_bytes()
    assert len(data) == 70 * frame_nbytes(13, 21)
    spikes = unpack_frames(data, 13, 21)
    rng = np.random.default_rng(3)
    scene = random_scene(rng, 13, 21, "slow")
    assert np.array_equal(spikes, simulate(scene, 70, SensorConfig.ideal(), rng))
    with np.load(tmp_path / "s.gt.npz") as npz:
        gt, meta = npz["gt"], json.loads(str(npz["meta"]))
    assert gt.dtype == np.float32 and gt.shape == (70, 13, 21)
    assert np.array_equal(gt, ground_truth(scene, range(70)))
    assert meta["scene"]["motion"] == "slow" and meta["sensor"]["preset"] == "ideal"


@pytest.mark.parametrize(
    "extra",
    [
        ["--frames", "0"],
        ["--height", "-2"],
        ["--sensor", "real", "--width", "0"],
        ["--height", "100000"],
        ["--seed", "-1"],
    ],
)
def test_simulate_cli_rejects_bad_arguments_in_one_line(tmp_path, capsys, extra):
    assert main(["simulate", str(tmp_path / "s.dat"), *extra]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("spk2img simulate: error:") and "\n" not in err
    assert not (tmp_path / "s.dat").exists()


def test_a_stopped_simulate_leaves_no_shorter_stream_under_the_name_asked_for(
    tmp_path, monkeypatch
):
    """Ctrl-C after the first chunk: the files of an earlier run stay as they were and no
    partial file is left; the same command then writes the whole stream."""
    from spk2img.cli import simulate as simulate_cli

    out = tmp_path / "s.dat"
    out.write_bytes(b"earlier")
    chunk, chunks = simulate_cli.pack_frames, []

    def stop_at_the_second_chunk(frames):
        chunks.append(len(frames))
        if len(chunks) == 2:
            raise KeyboardInterrupt
        return chunk(frames)

    monkeypatch.setattr(simulate_cli, "pack_frames", stop_at_the_second_chunk)
    args = ["simulate", str(out), "--frames", "70", "--height", "8", "--width", "8", "-q"]
    assert main(args) == 130 and len(chunks) == 2
    assert out.read_bytes() == b"earlier" and sorted(tmp_path.iterdir()) == [out]
    monkeypatch.undo()
    assert main(args) == 0 and len(out.read_bytes()) == 70 * frame_nbytes(8, 8)


def test_simulate_cli_rejects_a_missing_directory_and_a_wrong_suffix(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "nowhere" / "s.dat")]) != 0
    assert main(["simulate", str(tmp_path / "s.npy")]) != 0
    assert capsys.readouterr().err.count("error:") == 2


def test_every_seeded_window_set_has_its_own_seed():
    """The registry of seeded sets (spk2img.evaluation.window_sets) gives each set its own seed,
    and each builder films with the seed the registry gives it."""
    from spk2img.bench.cases import BENCH_SEED
    from spk2img.evaluation.natural_validation import NATURAL_SEED
    from spk2img.evaluation.scoring import TEST_SEED, VALIDATION_SEED
    from spk2img.evaluation.window_sets import WINDOW_SETS
    from spk2img.export.hard_cases import HARD_CASE_SEED
    from spk2img.export.quantize import CALIBRATION_SEED

    seeds = list(WINDOW_SETS.values())
    assert len(set(seeds)) == len(seeds) == 7
    used = {BENCH_SEED, NATURAL_SEED, TEST_SEED, VALIDATION_SEED, HARD_CASE_SEED, CALIBRATION_SEED}
    assert used | {WINDOW_SETS["real video"]} == set(seeds)
