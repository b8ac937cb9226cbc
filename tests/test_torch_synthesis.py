"""Spike synthesis in torch against the numpy simulator, the reference: the renderer gives the
same intensities, the sensor the same spikes where both are deterministic, and the same
statistics (rates per intensity, inter-spike intervals, fixed-pattern and hot-pixel noise)
where they draw noise from different generators."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.sim.natural_scenes import CLIP_MARGIN, clip_scene, photo_scene
from spk2img.sim.scenes import BRIGHTNESSES, MOTIONS, StillScene, random_scene
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.simulator import (
    SensorConfig,
    SpikeSimulator,
    ground_truth,
    simulate,
    substep_times,
)
from spk2img.sim.torch_render import render
from spk2img.sim.torch_sensor import SensorState, film
from spk2img.training.data import DataMix, SampleMaker, augment
from spk2img.training.synthesis import SUBSTEPS, batch_generator, film_plans

CPU = torch.device("cpu")
TIMES = substep_times(0.0, 41, SUBSTEPS)
RENDER_TOLERANCE = 2e-5
"""Largest intensity difference allowed between the two renderers (of 1): only the sums in the
source coordinates may round differently."""


def texture(height: int, width: int, seed: int) -> np.ndarray:
    """Smooth random ``(H, W) uint8`` texture (sums of sines)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    image = sum(np.sin(rng.uniform(-0.3, 0.3) * y + rng.uniform(-0.3, 0.3) * x) for _ in range(6))
    return np.uint8(np.clip(128 + 30 * image, 0, 255))


def assert_rendered_alike(scene) -> None:
    reference = np.asarray(scene.intensities(TIMES))
    rendered = render(scene, TIMES, CPU).numpy()
    assert rendered.shape == reference.shape
    assert np.abs(rendered - reference).max() <= RENDER_TOLERANCE


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    motion=st.sampled_from(MOTIONS),
    brightness=st.sampled_from(BRIGHTNESSES),
)
def test_procedural_and_photo_scenes_render_as_the_numpy_scenes_do(seed, motion, brightness):
    """Moving procedural content, and photos under camera motion with foreground layers."""
    rng = np.random.default_rng(seed)
    assert_rendered_alike(random_scene(rng, 24, 32, motion, brightness))
    photos = [np.float32(texture(60, 70, seed + k)) / 255 for k in range(4)]
    assert_rendered_alike(photo_scene(rng, photos, 24, 32, motion, brightness))


def test_clip_scenes_and_still_scenes_render_as_the_numpy_scenes_do():
    """A clip interpolated along its optical flow (a texture panning 2 px a video frame, eight
    video frames), in both light conventions; a still image."""
    big = texture(40 + 2 * CLIP_MARGIN, 120, 3)
    side = 40 + 2 * CLIP_MARGIN
    frames = tuple(big[:, 2 * k : 2 * k + side] for k in range(8))
    for seed, light in ((0, "linear"), (1, "display")):
        for motion in ("slow", "fast"):
            rng = np.random.default_rng(seed)
            assert_rendered_alike(clip_scene(rng, frames, 32, 32, motion, "normal", light))
    assert_rendered_alike(StillScene(np.float32(texture(20, 30, 1)) / 255))


@pytest.mark.parametrize(
    "sensor",
    [
        SensorConfig.ideal(),
        SensorConfig(
            dark_current=0.01, threshold_mismatch=0.05, hot_pixel_fraction=0.02, hot_pixel_rate=0.5
        ),
    ],
    ids=["ideal", "fixed-pattern noises"],
)
def test_the_sensor_fires_exactly_as_the_numpy_simulator_given_its_light_and_state(sensor):
    """Integrate-and-fire is deterministic given the light and the per-pixel state: the torch
    sensor, given the numpy simulator's, fires the same spikes, frame by frame."""
    scene = random_scene(np.random.default_rng(5), 30, 40, "fast", "normal")
    simulator = SpikeSimulator(scene, sensor, np.random.default_rng(6))
    per_pixel = (simulator.threshold, simulator.dark, simulator.charge)
    state = SensorState(*(torch.from_numpy(np.array(a))[None] for a in per_pixel))
    expected = simulator.run(41)
    light = torch.from_numpy(np.array(scene.intensities(TIMES))).reshape(1, 41, SUBSTEPS, 30, 40)
    spikes = film(light, [sensor], torch.Generator().manual_seed(0), state)[0].numpy()
    assert expected.sum() > 1000
    assert np.array_equal(spikes, expected)


def flat_field_statistics(spikes: np.ndarray) -> dict:
    """Per-level statistics of ``(T, H, W)`` spikes of a flat field."""
    rate = spikes.mean(0)
    intervals = np.concatenate(
        [np.diff(np.flatnonzero(col)) for col in spikes.reshape(len(spikes), -1).T]
    )
    histogram = np.bincount(np.minimum(intervals, 60), minlength=61) / max(1, len(intervals))
    return {
        "rate": float(rate.mean()),
        "pixel_spread": float(rate.std()),
        "busy_pixels": float((rate > 2 * np.median(rate) + 0.05).mean()),
        "isi": histogram,
    }


def test_the_sensors_agree_in_distribution_under_every_noise_of_the_fitted_preset():
    """Flat fields from dark to bright, filmed for 400 frames by the fitted real camera (shot
    noise, dark current, threshold mismatch, hot pixels): mean spike rate within 2 %, the
    spread of per-pixel rates within 10 %, the share of hot-looking pixels alike, and the
    inter-spike-interval histograms within 0.03 in total variation."""
    preset = load_preset(FITTED_PRESET)
    preset = SensorConfig(**{**preset.__dict__, "hot_pixel_fraction": 0.01})  # enough to count
    generator = torch.Generator().manual_seed(1)
    for level in (0.02, 0.1, 0.4, 0.9):
        scene = StillScene.uniform(96, 96, level)
        ours = simulate(scene, 400, preset, np.random.default_rng(2))
        light = torch.full((1, 400, SUBSTEPS, 96, 96), level)
        theirs = film(light, [preset], generator)[0].numpy()
        a, b = flat_field_statistics(ours), flat_field_statistics(theirs)
        assert b["rate"] == pytest.approx(a["rate"], rel=0.02)
        assert b["pixel_spread"] == pytest.approx(a["pixel_spread"], rel=0.1)
        assert b["busy_pixels"] == pytest.approx(a["busy_pixels"], abs=0.004)
        assert 0.5 * np.abs(a["isi"] - b["isi"]).sum() < 0.03


def test_plans_filmed_in_torch_are_the_numpy_samples_in_distribution_and_truth():
    """The same scenes and sensors as the numpy samples (noise-free and fitted): the ground
    truth equal after the same augmentation, each window's spike rate within 3 % of the numpy
    window's, and batches a function of seed, rank and step."""
    maker = SampleMaker(32, seed=3, mix=DataMix(), real_sensor=load_preset(FITTED_PRESET))
    plans = maker.plans(step=2, size=6)
    spikes, truth = film_plans(plans, PUBLISHED_GEOMETRY, batch_generator(3, 0, 2, CPU))
    assert spikes.shape == (6, 41, 32, 32) and truth.shape == (6, 5, 32, 32)
    assert set(torch.unique(spikes).tolist()) <= {0.0, 1.0}
    for item, plan in enumerate(plans):
        reference = augment(
            ground_truth(plan.scene, PUBLISHED_GEOMETRY.block_centres),
            plan.quarter_turns,
            plan.mirror,
        )
        assert np.abs(truth[item].numpy() - reference).max() <= RENDER_TOLERANCE
        numpy_spikes, _ = maker.sample(2, item)
        assert float(spikes[item].mean()) == pytest.approx(numpy_spikes.mean(), rel=0.03, abs=2e-3)
    again, _ = film_plans(maker.plans(2, 6), PUBLISHED_GEOMETRY, batch_generator(3, 0, 2, CPU))
    other, _ = film_plans(maker.plans(2, 6), PUBLISHED_GEOMETRY, batch_generator(3, 0, 3, CPU))
    assert torch.equal(spikes, again) and not torch.equal(spikes, other)
