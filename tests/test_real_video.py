"""The real-video validation (spk2img.evaluation.real_video): the field's light convention, the
clip's own motion brought to each speed bin, the window in the middle of the clip, the truth
the renderer defines, and the clips kept out of training."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis.extra.numpy import arrays
from PIL import Image
from script_loader import load_script

from spk2img.evaluation.natural_validation import NEVER_TRAINED
from spk2img.evaluation.real_video import (
    REAL_VIDEO_CLIPS,
    SPEEDS,
    RealVideoWindow,
    film,
    find_real_video_clips,
    load_windows,
    real_video_scenes,
    real_video_scores,
    real_video_set,
    save_windows,
    training_windows,
)
from spk2img.io.light import SPIKE_RATE
from spk2img.sim.natural_scenes import CLIP_MARGIN
from spk2img.sim.simulator import FILM_FRAMES
from spk2img.sim.sources import SourceIndex, to_light
from spk2img.training.model_card import real_video_section

H, W = 64, 96
ROOT = Path(__file__).resolve().parents[1]


def moving_texture(frames: int, px_per_frame: float) -> tuple[np.ndarray, ...]:
    """``frames`` uint8 frames of a smooth texture translating right by ``px_per_frame``."""
    y, x = np.mgrid[:H, :W].astype(np.float64)
    out = []
    for k in range(frames):
        u = x - k * px_per_frame
        value = 128 + 60 * np.sin(u / 3.1) * np.cos(y / 4.3) + 40 * np.sin((u + 2 * y) / 7.7)
        out.append(np.clip(value, 0, 255).astype(np.uint8))
    return tuple(out)


@given(arrays(np.uint8, (3, 5)))
def test_display_light_is_the_frame_value_over_255(grey):
    light = to_light(grey, "display")
    assert light.dtype == np.float32
    np.testing.assert_array_equal(light, grey.astype(np.float32) / 255)


@pytest.mark.parametrize("speed_bin", list(SPEEDS))
def test_the_clip_moves_at_the_bin_speed_where_it_is_long_enough(speed_bin):
    frames = moving_texture(20, 1.0)
    (scene,) = real_video_scenes("synthetic", frames, (speed_bin,), FILM_FRAMES)
    per_interval = scene.scene.frames_per_interval
    measured = scene.speed * per_interval  # the clip's median flow, px a video frame
    assert measured == pytest.approx(1.0, abs=0.1)
    assert scene.speed <= SPEEDS[speed_bin] + 1e-9
    if per_interval > FILM_FRAMES / 19:  # the bin's speed fits: exactly it
        assert scene.speed == pytest.approx(SPEEDS[speed_bin])
    else:  # too short a clip for that speed: the window spans the whole clip
        assert per_interval == pytest.approx(FILM_FRAMES / 19)
    # the window sits in the middle of the clip's time
    span = 19 * per_interval
    assert scene.scene.start == pytest.approx((span - FILM_FRAMES) / 2)


def test_a_still_clip_fires_at_0_6_value_over_255_and_its_truth_is_the_frame():
    value = 200
    frames = tuple(np.full((H, W), value, np.uint8) for _ in range(5))
    (scene,) = real_video_scenes("still", frames, ("benchmark",), FILM_FRAMES)
    window = film(scene, seed=0)
    assert window.spikes.shape == (FILM_FRAMES, H - 2 * CLIP_MARGIN, W - 2 * CLIP_MARGIN)
    rate = window.spikes.mean(axis=0)
    np.testing.assert_allclose(rate, SPIKE_RATE * value / 255, atol=1 / FILM_FRAMES + 1e-6)
    np.testing.assert_allclose(window.truth, value / 255, atol=1e-6)
    assert not np.array_equal(window.spikes, film(scene, seed=1).spikes)  # another start charge
    np.testing.assert_array_equal(window.spikes, film(scene, seed=0).spikes)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """A data folder with two validation clips (as numbered frames) and a clip of another name."""
    root = tmp_path_factory.mktemp("data")
    for name in ("vid4_walk", "x4k1000fps_TEST02_045_f0465", "my_clip"):
        (root / name).mkdir()
        for k, frame in enumerate(moving_texture(6, 0.5)):
            Image.fromarray(frame).save(root / name / f"{k:05d}.png")
    return root


def test_the_clips_are_found_in_registry_order_and_never_trained_on(data_dir):
    found = find_real_video_clips([data_dir])
    assert [c.name for c in found] == ["x4k1000fps_TEST02_045_f0465", "vid4_walk"]
    assert set(REAL_VIDEO_CLIPS) <= NEVER_TRAINED
    training = SourceIndex.scan([data_dir], 8, NEVER_TRAINED)
    assert [c.name for c in training.clips] == ["my_clip"]


def test_the_set_films_every_clip_at_every_bin_and_seed(data_dir):
    windows = real_video_set([data_dir], seeds=2)
    assert [(w.clip, w.speed_bin, w.seed) for w in windows] == [
        (clip, b, seed)
        for clip in ("x4k1000fps_TEST02_045_f0465", "vid4_walk")
        for b in SPEEDS
        for seed in (0, 1)
    ]
    for w in windows:
        assert set(np.unique(w.spikes)) <= {0, 1} and np.isfinite(w.truth).all()
        assert w.spikes.shape == (FILM_FRAMES, H - 2 * CLIP_MARGIN, W - 2 * CLIP_MARGIN)
    cropped = real_video_set([data_dir], seeds=1, size=(16, 24))
    assert [w.spikes.shape for w in cropped] == [(FILM_FRAMES, 16, 24)] * 4
    assert [w.truth.shape for w in cropped] == [(16, 24)] * 4


def test_training_windows_travel_in_a_file_and_come_back_the_same(data_dir, tmp_path):
    """``save_windows`` / ``load_windows``: the training crops of the clips, bit for bit (the
    spikes packed 8 to a byte), so a run without the clips validates on the same windows; a
    file that is not one is named."""
    windows = training_windows([data_dir])
    path = tmp_path / "windows.npz"
    save_windows(windows, path)
    back = load_windows(path)
    assert [(w.clip, w.speed_bin, w.speed, w.seed) for w in back] == [
        (w.clip, w.speed_bin, w.speed, w.seed) for w in windows
    ]
    for got, filmed in zip(back, windows, strict=True):
        assert got.spikes.dtype == np.uint8 and np.array_equal(got.spikes, filmed.spikes)
        assert np.array_equal(got.truth, filmed.truth)
    assert path.stat().st_size < sum(w.spikes.size // 8 + w.truth.nbytes for w in windows)
    (tmp_path / "other.npz").write_bytes(b"not an archive")
    with pytest.raises(ValueError, match="other.npz: not a file of real-video windows"):
        load_windows(tmp_path / "other.npz")


def test_scores_per_bin_clip_and_seed_and_the_cards_section():
    """An image 0.01 off the truth everywhere scores 40 dB in every bin, clip and seed."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.2, 0.8, (16, 16)).astype(np.float32)
    spikes = np.zeros((FILM_FRAMES, 16, 16), np.uint8)
    windows = [
        RealVideoWindow(clip, b, SPEEDS[b], seed, spikes, truth)
        for clip in ("a", "b")
        for b in SPEEDS
        for seed in (0, 1)
    ]
    scores = real_video_scores(windows, [w.truth + 0.01 for w in windows])
    assert scores["psnr"] == pytest.approx(40.0, abs=1e-3)
    assert scores["seed_psnr"] == pytest.approx([40.0, 40.0], abs=1e-3)
    assert scores["seed_std_db"] == pytest.approx(0.0, abs=1e-6)
    for b in SPEEDS:
        assert set(scores["speed_bins"][b]["clips"]) == {"a", "b"}
        assert scores["speed_bins"][b]["clip_std_db"] == pytest.approx(0.0, abs=1e-6)
    section = real_video_section({"network": scores, "TFI": scores})
    assert (
        "| network | 40.00 | " in section and "Per clip, benchmark bin: a 40.0, b 40.0" in section
    )


def test_the_script_scores_a_graph_by_path_beside_the_shipped_model_it_is(data_dir, tmp_path):
    """``--models tiny,candidate=GRAPH.onnx`` (the shipped ``tiny``'s own graph): the same
    scores under both names; ``--add`` keeps them and the written notes, lists each date once
    and refuses a JSON scored on other windows."""
    script = load_script("real_video_validation")
    graph = ROOT / "spk2img/assets/models/spk2img-tiny.onnx"
    out = ["--json", str(tmp_path / "rv.json"), "--md", str(tmp_path / "rv.md")]
    data = ["--data", str(data_dir), "--threads", "1", *out]
    base = [*data, "--seeds", "1"]
    script.main([*base, "--models", f"tiny,candidate={graph}"])
    methods = json.loads((tmp_path / "rv.json").read_text())["methods"]
    assert list(methods) == ["TFP-41", "TFP, best window (oracle)", "TFI", "tiny", "candidate"]
    assert methods["candidate"]["psnr"] == pytest.approx(methods["tiny"]["psnr"], abs=1e-9)
    assert methods["tiny"]["psnr"] > methods["TFP-41"]["psnr"]
    (tmp_path / "rv.md").write_text((tmp_path / "rv.md").read_text() + "\n## Reading it\nkept\n")
    script.main([*base, "--models", f"again={graph}", "--add"])
    written = json.loads((tmp_path / "rv.json").read_text())
    assert list(written["methods"])[-1] == "again" and " and " not in written["date"]
    assert (tmp_path / "rv.md").read_text().endswith("## Reading it\nkept\n")
    with pytest.raises(SystemExit, match="other windows or seeds"):
        script.main([*data, "--seeds", "2", "--models", "tiny", "--add"])
