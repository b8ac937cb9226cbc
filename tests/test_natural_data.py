"""Natural training content: the folder index, photo and clip scenes, the training mix and
training from folders. The tests make their own tiny photo and clip folders."""

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from spk2img.cli import build_parser, main
from spk2img.cli.extras import required_extra
from spk2img.evaluation.metrics import psnr
from spk2img.sim.natural_scenes import (
    CLIP_MARGIN,
    ClipScene,
    clip_scene,
    dis_flow,
    photo_scene,
)
from spk2img.sim.scenes import PROCEDURAL_KINDS
from spk2img.sim.simulator import GT_FRAMES, ground_truth
from spk2img.sim.sources import (
    LIGHT_CONVENTIONS,
    FrameFolder,
    SourceIndex,
    VideoFile,
    load_clip,
    load_photo,
    read_video,
    to_light,
)
from spk2img.training.data import DataMix, SampleMaker

RNG = np.random.default_rng(0)


def texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """Smooth random texture ``(H, W) uint8`` (sums of sines: optical flow can follow it)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    image = np.zeros((height, width), np.float32)
    for _ in range(6):
        ky, kx = rng.uniform(-0.3, 0.3, 2)
        image += np.sin(ky * y + kx * x + rng.uniform(0, 6))
    return np.uint8(np.clip(128 + 30 * image, 0, 255))


def write_mp4(path: Path, frames: list[np.ndarray]) -> None:
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=25)
        stream.height, stream.width = frames[0].shape
        stream.pix_fmt = "yuv420p"
        for grey in frames:
            frame = av.VideoFrame.from_ndarray(np.repeat(grey[..., None], 3, 2), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data")
    photos = root / "photos"
    photos.mkdir()
    rgb = np.stack([texture(90, 120, s) for s in (1, 2, 3)], -1)
    Image.fromarray(rgb).save(photos / "colour.png")
    Image.fromarray(texture(100, 80, 4)).save(photos / "grey.jpg")
    Image.fromarray(texture(100, 100, 5)).save(photos / "kodak24_kodim08.png")  # held out
    Image.fromarray(texture(20, 20, 6)).save(photos / "small.png")
    (photos / "broken.png").write_bytes(b"not a png at all")
    clip = root / "video" / "walk"
    clip.mkdir(parents=True)
    for k in range(5):
        Image.fromarray(texture(96, 128, 7)[:, k : k + 100]).save(clip / f"{k:05d}.png")
    reds = root / "train_sharp" / "000"
    reds.mkdir(parents=True)
    for k in range(3):
        Image.fromarray(texture(80, 80, 8 + k)).save(reds / f"{k:08d}.png")
    write_mp4(root / "pan.mp4", [texture(64, 96, 11)[:, k : k + 80].copy() for k in range(6)])
    return root


def test_the_index_finds_photos_frame_folders_and_videos_and_skips_bad_files(data_dir):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = SourceIndex.scan(
            [data_dir], min_side=32, held_out=frozenset({"kodak24_kodim08.png"})
        )
    assert sorted(p.path.name for p in index.photos) == ["colour.png", "grey.jpg"]
    kinds = {type(c).__name__: c for c in index.clips}
    assert set(kinds) == {"FrameFolder", "VideoFile"} and len(index.clips) == 3
    folders = sorted(c.name for c in index.clips if isinstance(c, FrameFolder))
    assert folders == ["000", "walk"]
    assert index.skipped == {"unreadable": 1, "too small": 1, "held out": 1}
    assert any("skipped" in str(w.message) for w in caught)
    assert index.summary()["video_files"] == 1


def test_without_pyav_a_run_skips_its_video_files_and_says_why(data_dir, monkeypatch):
    """The GPU machines' image has no PyAV: ``spk2img train`` still runs there (it needs torch
    and OpenCV only) and a video file is one more unreadable source, named with the reason."""
    monkeypatch.setitem(sys.modules, "av", None)  # import av: ImportError
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = SourceIndex.scan([data_dir], min_side=32)
    assert index.summary()["video_files"] == 0 and len(index.clips) == 2
    assert index.skipped["unreadable"] == 2  # broken.png and pan.mp4
    (said,) = [str(w.message) for w in caught if "pan.mp4" in str(w.message)]
    assert said.endswith("(video files need PyAV, the train extra)")
    need = required_extra(build_parser().parse_args(["train", "--steps", "1"]))
    assert "av" not in need.modules and {"torch", "cv2"} <= set(need.modules)


def test_frames_are_luminance_made_light_by_either_convention(data_dir):
    """``linear`` undoes the display gamma, ``display`` takes value / 255 as the light; both
    keep black and white; an unknown convention is refused."""
    for convention in LIGHT_CONVENTIONS:
        assert to_light(np.array([[0, 255]], np.uint8), convention).tolist() == [[0.0, 1.0]]
    assert to_light(np.array([[128]], np.uint8))[0, 0] == pytest.approx((128 / 255) ** 2.2)
    assert to_light(np.array([[128]], np.uint8), "display")[0, 0] == pytest.approx(128 / 255)
    with pytest.raises(ValueError, match="light convention"):
        to_light(np.array([[128]], np.uint8), "srgb")
    video = read_video(data_dir / "pan.mp4")
    assert len(video) == 6 and video[0].shape == (64, 80) and video[0].dtype == np.uint8
    expected = texture(64, 96, 11)[:, :80].astype(float)
    assert np.abs(video[0] - expected).mean() < 6  # lossy codec, same picture
    assert len(load_clip(VideoFile(data_dir / "pan.mp4"))) == 6


def test_photo_scenes_move_and_their_layers_occlude():
    photos = [to_light(texture(120, 160, s)) for s in range(4)]
    still = photo_scene(np.random.default_rng(1), photos, 32, 40, "static", "normal")
    frames = still.intensities([0.5, 20.5, 40.5])
    assert np.array_equal(frames[0], frames[2])
    moving = None
    for seed in range(20):  # a scene with layers
        moving = photo_scene(np.random.default_rng(seed), photos, 32, 40, "fast", "bright")
        if moving.meta["layers"]:
            break
    assert moving.meta["layers"] >= 1
    frames = moving.intensities([0.5, 40.5])
    assert frames.shape == (2, 32, 40) and 0 <= frames.min() and frames.max() <= 1
    assert np.abs(frames[0] - frames[1]).mean() > 0.01
    background = moving.background.intensities([0.5])[0]
    content, alpha = moving.layers[0]
    covered = alpha.intensities([0.5])[0] > 0.99
    if covered.any():  # where the first layer covers, the background is gone
        assert not np.allclose(frames[0][covered], background[covered])


def test_clip_interpolation_moves_content_along_the_flow():
    """A texture translating 3 px a frame: halfway between two frames the interpolation is the
    texture shifted 1.5 px, much closer to it than a cross-fade."""
    big = texture(64 + 2 * CLIP_MARGIN, 120, 3)
    frames = [big[:, 12 - 3 * k : 12 - 3 * k + 64 + 2 * CLIP_MARGIN] for k in range(2)]
    forward = np.stack([dis_flow(frames[0], frames[1])])
    backward = np.stack([dis_flow(frames[1], frames[0])])
    assert np.median(forward[..., 0]) == pytest.approx(3, abs=0.3)
    linear = np.stack([to_light(f) for f in frames])
    scene = ClipScene(linear, forward, backward, frames_per_interval=10, start=0, meta={})
    halfway = scene.intensity(5.0)
    m = CLIP_MARGIN
    shifted = Image.fromarray(to_light(big)).transform(
        big.shape[::-1], Image.Transform.AFFINE, (1, 0, 10.5, 0, 1, 0), Image.Resampling.BILINEAR
    )
    truth = np.asarray(shifted)[m:-m, m : m + 64]
    crossfade = (0.5 * linear[0] + 0.5 * linear[1])[m:-m, m:-m]
    assert psnr(halfway, truth) > psnr(crossfade, truth) + 6
    assert np.allclose(scene.intensity(0.0), linear[0][m:-m, m:-m], atol=1e-5)


def test_clip_scenes_take_the_motion_class_where_the_clip_allows():
    frames = tuple(texture(96, 200, 9)[:, 80 - 8 * k : 180 - 8 * k].copy() for k in range(10))
    speeds = {}
    for motion in ("static", "slow", "fast"):
        scene = clip_scene(np.random.default_rng(2), frames, 48, 48, motion, "normal")
        speeds[motion] = scene.meta["speed"]
        truth = ground_truth(scene, GT_FRAMES)
        assert truth.shape == (5, 48, 48) and np.isfinite(truth).all()
    assert speeds["static"] < 1e-6 < speeds["slow"] < speeds["fast"]
    assert 0.5 <= speeds["fast"] <= 3.5


def test_data_mix():
    mix = DataMix.parse("photos=0.5,clips=0.3,procedural=0.2")
    assert mix.weights().tolist() == pytest.approx([0.2, 0.5, 0.3])
    for bad in ("photos=x", "faces=1", "photos=-1", "photos=0", "photos"):
        with pytest.raises(ValueError):
            DataMix.parse(bad)
    assert "natural" not in PROCEDURAL_KINDS


def test_samples_draw_every_kind_and_fall_back_to_procedural(data_dir):
    index = SourceIndex.scan([data_dir], min_side=32)
    maker = SampleMaker(16, seed=0, mix=DataMix(1, 1, 1), index=index)
    spikes, truth = maker.batch(0, 6)
    assert spikes.shape == (6, 41, 16, 16) and truth.shape == (6, 5, 16, 16)
    assert set(np.unique(spikes)) <= {0.0, 1.0} and 0 <= truth.min() and truth.max() <= 1
    assert SampleMaker(16, 0, mix=DataMix(0, 1, 1), index=None).weights.tolist() == [1, 0, 0]


def test_a_file_that_breaks_after_indexing_gives_a_procedural_sample(tmp_path):
    good = tmp_path / "good.png"
    Image.fromarray(texture(80, 80, 1)).save(good)
    index = SourceIndex.scan([tmp_path], min_side=16)
    good.write_bytes(good.read_bytes()[:100])  # truncated: the header still reads
    load_photo.cache_clear()
    maker = SampleMaker(16, seed=0, mix=DataMix(0, 1, 0), index=index)
    with pytest.warns(UserWarning, match="procedural sample instead"):
        spikes, truth = maker.batch(0, 2)
    assert spikes.shape == (2, 41, 16, 16) and np.isfinite(truth).all()


def test_train_from_folders_selects_on_the_natural_validation(tmp_path, data_dir):
    run = tmp_path / "run"
    flags = "--member tiny --steps 2 --patch 16 --batch-size 2 --val-every 2 --val-per-class 1"
    args = ["train", *flags.split(), "--workers", "0", "--no-progress"]
    assert main([*args, "--run-dir", str(run), "--data", str(data_dir)]) == 0
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    (data,) = [r for r in records if r["kind"] == "data"]
    assert data["sources"]["photos"] == 3 and data["sources"]["clips"] == 3  # 20 px fits 16
    assert data["sources"]["skipped"]["held out"] == 1
    assert data["natural_validation_scenes"] == 6  # one held-out photo x 3 motions x 2 regimes
    (val,) = [r for r in records if r["kind"] == "val"]
    assert set(val["natural"]) >= {"psnr", "psnr_ideal", "psnr_fitted"}
    import torch

    best = torch.load(run / "best.pt", weights_only=True)
    assert best["val_set"] == "natural" and best["val_psnr"] == val["natural"]["psnr"]
    noise_free = tmp_path / "noise_free"  # an ideal-only run chooses on the ideal regime
    ideal = ["--run-dir", str(noise_free), "--data", str(data_dir), "--ideal-share", "1"]
    assert main([*args, *ideal]) == 0
    best = torch.load(noise_free / "best.pt", weights_only=True)
    lines = (noise_free / "metrics.jsonl").read_text().splitlines()
    (val,) = [r for r in map(json.loads, lines) if r["kind"] == "val"]
    assert best["val_set"] == "natural ideal"
    assert best["val_psnr"] == val["natural"]["psnr_ideal"] != val["natural"]["psnr"]
    # with a real-video clip in the data, a noise-free run chooses on the real-video validation
    # and never trains on that clip; with --ema-decay it scores the average, the trained
    # weights beside it
    clips = tmp_path / "clips" / "vid4_walk"
    clips.mkdir(parents=True)
    for k in range(6):
        Image.fromarray(texture(64, 72, 10 + k)).save(clips / f"{k:05d}.png")
    real_video = tmp_path / "real_video"
    flags = ["--run-dir", str(real_video), "--data", str(tmp_path / "clips"), *ideal[2:]]
    flags += ["--ema-decay", "0.5"]
    assert main([*args, *flags]) == 0
    records = [json.loads(line) for line in (real_video / "metrics.jsonl").read_text().splitlines()]
    (data,) = [r for r in records if r["kind"] == "data"]
    assert data["real_video_windows"] == 2  # one clip x two speed bins x one seed
    assert data["sources"]["skipped"]["held out"] == 2  # the real-video clip is not trained on
    (val,) = [r for r in records if r["kind"] == "val"]
    best = torch.load(real_video / "best.pt", weights_only=True)
    assert best["val_set"] == "real video" and best["val_psnr"] == val["real_video"]["psnr"]
    assert set(val["real_video"]["speed_bins"]) == {"benchmark", "fast"}
    trained = val["real_video_trained"]
    assert set(trained["speed_bins"]) == {"benchmark", "fast"}
    assert trained["psnr"] != val["real_video"]["psnr"]  # two steps: the average lags behind


def test_train_refuses_cuda_without_a_gpu_and_bad_mixes(tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert main(["train", "--run-dir", str(tmp_path), "--device", "cuda"]) == 2
    assert main(["train", "--run-dir", str(tmp_path), "--data-mix", "faces=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "no CUDA device" in err[0] and "faces" in err[1]
