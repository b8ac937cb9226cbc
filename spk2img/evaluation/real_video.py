"""The real-video validation: held-out real clips, filmed with their own motion at their stored
resolution, under the field's light convention.

The benchmark this project is judged on simulates spike streams from real video with the 8-bit
frame value as the light (a pixel of value ``v`` fires ``0.6 * v / 255`` spikes a frame, no
display gamma undone) and real, non-uniform motion of about 0.14 px a spike frame on texture-rich
scenes. The natural validation (:mod:`.natural_validation`) pans photographs and crops clips
with linear light, and its scores did not predict that benchmark's. Here:

- **Clips**: :data:`REAL_VIDEO_CLIPS`, 15 real 1000 frame/s clips (X4K1000FPS X-TEST, 33 frames
  each) and the 4 Vid4 clips, whole frames (less a margin of :data:`~spk2img.sim.natural_scenes.
  CLIP_MARGIN` pixels for the flow), never trained on (training skips them whatever ``--data``
  holds).
- **Light**: display-referred, ``value / 255`` (:func:`~spk2img.sim.sources.to_light`'s
  ``display`` convention).
- **Motion**: the clip's own, interpolated between video frames along its optical flow
  (:class:`~spk2img.sim.natural_scenes.ClipScene`). The spike frames per video interval are set
  so that the clip's median flow magnitude is each speed of :data:`SPEEDS` px a spike frame,
  where the clip is long enough (a window must fit in it: slow clips stay slower).
- **Sensor**: noise-free integrate-and-fire; the window in the middle of the clip; the truth at
  its centre frame (:data:`~spk2img.sim.simulator.CENTER_FRAME`) as the renderer defines it.
- **Seeds**: each seed of :func:`real_video_set` draws the sensor's initial charge: the spread
  over seeds says how stable a score is.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img.evaluation.scoring import group_scores, image_scores, mean_scores
from spk2img.evaluation.window_sets import seed_of
from spk2img.sim.natural_scenes import CLIP_MARGIN, ClipScene, dis_flow
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES, SensorConfig, ground_truth, simulate
from spk2img.sim.sources import FrameFolder, SourceIndex, load_clip, to_light

X4K_CLIPS = (
    "x4k1000fps_TEST01_003_f0433",
    "x4k1000fps_TEST02_045_f0465",
    "x4k1000fps_TEST03_081_f4833",
    "x4k1000fps_TEST04_140_f3889",
    "x4k1000fps_TEST05_158_f0321",
    "x4k1000fps_TEST06_001_f0273",
    "x4k1000fps_TEST07_076_f1889",
    "x4k1000fps_TEST08_079_f0321",
    "x4k1000fps_TEST09_112_f0177",
    "x4k1000fps_TEST10_172_f1905",
    "x4k1000fps_TEST11_078_f4977",
    "x4k1000fps_TEST12_087_f2721",
    "x4k1000fps_TEST13_133_f4593",
    "x4k1000fps_TEST14_146_f1761",
    "x4k1000fps_TEST15_148_f0465",
)
"""X4K1000FPS X-TEST (research and education only: never trained on)."""
VID4_CLIPS = ("vid4_calendar", "vid4_city", "vid4_foliage", "vid4_walk")
"""Vid4 (texture-rich; no licence stated for the frames: never trained on)."""
REAL_VIDEO_CLIPS = X4K_CLIPS + VID4_CLIPS
"""The clips of the real-video validation, by folder name."""
SPEEDS = {"benchmark": 0.14, "fast": 1.0}
"""Speed bin -> median flow magnitude in px a spike frame: the benchmark's camera pans, and
about seven times faster motion (capped, like any bin, by what a window in the clip allows:
0.19-0.94 px a spike frame on these clips)."""
SEEDS = 3
"""Draws of the sensor's initial charge per window by default."""
TRAINING_CROP = (96, 128)
"""Height and width of the centre crops of the clips that training validates on
(:func:`training_windows`; the whole frames are scored by the model card and
scripts/real_video_validation.py)."""


@dataclass(frozen=True)
class RealVideoScene:
    """One clip filmed at one speed bin."""

    clip: str
    speed_bin: str
    speed: float
    """Median flow magnitude over the window, px a spike frame (below the bin's where the clip
    is too slow)."""
    scene: ClipScene


@dataclass(frozen=True)
class RealVideoWindow:
    """One filmed window of a :class:`RealVideoScene`."""

    clip: str
    speed_bin: str
    speed: float
    """The scene's speed, px a spike frame (:attr:`RealVideoScene.speed`)."""
    seed: int
    spikes: np.ndarray
    """``(FILM_FRAMES, H, W) uint8`` 0/1."""
    truth: np.ndarray
    """``(H, W) float32`` light at the centre frame."""


def real_video_scenes(
    name: str, frames: tuple[np.ndarray, ...], speed_bins: tuple[str, ...], window: int
) -> list[RealVideoScene]:
    """Clip ``name``'s ``(H, W) uint8`` frames as a scene at each of ``speed_bins``: moving at
    ``SPEEDS[bin]`` px a spike frame (or as fast as a ``window``-frame window in the clip
    allows), the window in the middle of the clip, light by the ``display`` convention; the
    clip's flows computed once."""
    if len(frames) < 2:
        raise ValueError(f"clip {name} has {len(frames)} frame(s): at least 2 are needed")
    forward = np.stack([dis_flow(a, b) for a, b in zip(frames, frames[1:], strict=False)])
    backward = np.stack([dis_flow(b, a) for a, b in zip(frames, frames[1:], strict=False)])
    light = np.stack([to_light(f, "display") for f in frames])
    per_video_frame = float(np.median(np.linalg.norm(forward, axis=-1)))
    intervals = len(frames) - 1
    scenes = []
    for speed_bin in speed_bins:
        per_interval = max(window / intervals, per_video_frame / SPEEDS[speed_bin])
        start = (intervals * per_interval - window) / 2  # the window in the middle of the clip
        speed = per_video_frame / per_interval
        meta = {"kind": "real video", "clip": name, "speed": speed, "speed_bin": speed_bin}
        meta["frames_per_interval"] = per_interval
        scene = ClipScene(light, forward, backward, per_interval, start, meta)
        scenes.append(RealVideoScene(name, speed_bin, speed, scene))
    return scenes


def centre_crop(frames: tuple[np.ndarray, ...], size: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """The centred ``size`` (height, width) of each frame, plus the flow's margin on each side
    (the whole frame where it is smaller)."""
    height, width = frames[0].shape
    h, w = (min(s + 2 * CLIP_MARGIN, full) for s, full in zip(size, (height, width), strict=True))
    top, left = (height - h) // 2, (width - w) // 2
    return tuple(f[top : top + h, left : left + w] for f in frames)


def find_real_video_clips(folders: list[str | Path]) -> list[FrameFolder]:
    """The clips of :data:`REAL_VIDEO_CLIPS` found under ``folders``, in that order."""
    found: dict[str, FrameFolder] = {}
    for folder in folders:
        index = SourceIndex.scan([folder], min_side=0)
        found |= {c.name: c for c in index.clips if c.name in REAL_VIDEO_CLIPS}
    return [found[name] for name in REAL_VIDEO_CLIPS if name in found]


def film(scene: RealVideoScene, seed: int) -> RealVideoWindow:
    """``scene`` filmed by the noise-free sensor over :data:`FILM_FRAMES` frames, the sensor's
    initial charge drawn from ``seed``, with its truth at the centre frame."""
    rng = np.random.default_rng([seed_of("real video"), seed])
    spikes = simulate(scene.scene, FILM_FRAMES, SensorConfig.ideal(), rng)
    truth = ground_truth(scene.scene, [CENTER_FRAME])[0]
    return RealVideoWindow(scene.clip, scene.speed_bin, scene.speed, seed, spikes, truth)


def real_video_set(
    folders: list[str | Path],
    seeds: int = SEEDS,
    speed_bins: tuple[str, ...] = tuple(SPEEDS),
    size: tuple[int, int] | None = None,
) -> list[RealVideoWindow]:
    """The window of each clip of :data:`REAL_VIDEO_CLIPS` under ``folders`` at each speed bin,
    filmed once per seed ``0 .. seeds - 1`` (clip by clip, bin by bin); empty when ``folders``
    hold none of the clips. ``size`` (height, width): the centred crop of each clip to film
    (:func:`centre_crop`; its motion measured there), a cheaper set for validating during
    training; None: the whole frames."""
    windows = []
    for clip in find_real_video_clips(folders):
        frames = load_clip(clip)
        if size is not None:
            frames = centre_crop(frames, size)
        for scene in real_video_scenes(clip.name, frames, speed_bins, FILM_FRAMES):
            windows += [film(scene, seed) for seed in range(seeds)]
    return windows


def real_video_scores(windows: list[RealVideoWindow], images: list[np.ndarray]) -> dict:
    """PSNR (dB) and SSIM of one method's ``images`` (one ``(H, W)`` image per window, in order):
    over all windows (``psnr``, ``ssim``); the overall PSNR of each seed (``seed_psnr``) and
    their standard deviation (``seed_std_db``); per speed bin (``speed_bins[bin]``: ``psnr``,
    ``ssim``, the standard deviation of the per-clip means ``clip_std_db``, and ``clips[clip]``:
    ``psnr``, ``ssim`` over its seeds)."""
    scores = image_scores(images, [w.truth for w in windows])
    seeds = sorted({w.seed for w in windows})
    per_seed = [
        mean_scores([s for s, w in zip(scores, windows, strict=True) if w.seed == seed])["psnr"]
        for seed in seeds
    ]
    clips = list(dict.fromkeys(w.clip for w in windows))
    per_bin = {}
    for speed_bin in SPEEDS:
        picked = [(s, w) for s, w in zip(scores, windows, strict=True) if w.speed_bin == speed_bin]
        if not picked:
            continue
        by_clip = group_scores([s for s, _ in picked], [w.clip for _, w in picked], clips)
        clip_psnr = [v["psnr"] for v in by_clip.values()]
        per_bin[speed_bin] = {
            **mean_scores([s for s, _ in picked]),
            "clip_std_db": float(np.std(clip_psnr)),
            "clips": by_clip,
        }
    return {
        **mean_scores(scores),
        "seed_psnr": per_seed,
        "seed_std_db": float(np.std(per_seed)),
        "speed_bins": per_bin,
    }


def training_windows(folders: list[str | Path]) -> list[RealVideoWindow]:
    """The real-video windows training validates on: one seed, the :data:`TRAINING_CROP` of
    each clip under ``folders``, at each speed bin."""
    return real_video_set(folders, seeds=1, size=TRAINING_CROP)


def save_windows(windows: list[RealVideoWindow], path: str | Path) -> None:
    """Write ``windows`` (all of one size) to the ``.npz`` file ``path``: the spikes packed 8 to
    a byte, the rest as it is, so that a machine without the clips validates on the same
    windows (:func:`load_windows`)."""
    spikes = np.stack([w.spikes for w in windows])
    np.savez_compressed(
        path,
        clip=np.array([w.clip for w in windows]),
        speed_bin=np.array([w.speed_bin for w in windows]),
        speed=np.array([w.speed for w in windows], np.float64),
        seed=np.array([w.seed for w in windows], np.int64),
        spikes=np.packbits(spikes, axis=-1),
        width=np.int64(spikes.shape[-1]),
        truth=np.stack([w.truth for w in windows]).astype(np.float32),
    )


def load_windows(path: str | Path) -> list[RealVideoWindow]:
    """The windows :func:`save_windows` wrote to ``path``; ``ValueError`` naming the file
    where it is not such a file."""
    try:
        with np.load(path, allow_pickle=False) as stored:
            spikes = np.unpackbits(stored["spikes"], axis=-1, count=int(stored["width"]))
            fields = zip(
                stored["clip"],
                stored["speed_bin"],
                stored["speed"],
                stored["seed"],
                spikes,
                stored["truth"],
                strict=True,
            )
            return [
                RealVideoWindow(str(c), str(b), float(v), int(s), frames, truth)
                for c, b, v, s, frames, truth in fields
            ]
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a file of real-video windows ({exc})") from None
