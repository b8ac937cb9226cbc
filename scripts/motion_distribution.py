"""Measure the motion (px/frame) of the training scenes: ``python scripts/motion_distribution.py
DATA_DIR [--samples N]`` prints, per content kind and motion class, the percentiles of the mean
speed of the scenes that ``spk2img train --data DATA_DIR`` draws (docs/training_data.md)."""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from spk2img.evaluation.natural_validation import HELD_OUT
from spk2img.sim.natural_scenes import MAX_LAYERS, clip_scene, photo_scene
from spk2img.sim.scenes import MOTIONS
from spk2img.sim.sources import SourceIndex, load_clip, load_photo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("data")
    parser.add_argument("--samples", type=int, default=150, help="per kind and motion class")
    parser.add_argument("--patch", type=int, default=64)
    args = parser.parse_args()
    index = SourceIndex.scan([args.data], args.patch, HELD_OUT)
    rng = np.random.default_rng(0)
    speeds = defaultdict(list)
    p = args.patch
    for motion in MOTIONS:
        for _ in range(args.samples):
            picks = rng.integers(len(index.photos), size=1 + MAX_LAYERS)
            photos = [load_photo(index.photos[k].path) for k in picks]
            scene = photo_scene(rng, photos, p, p, motion, "normal")
            speeds["photos", motion].append(scene.meta["speed"])
            clip = index.clips[int(rng.integers(len(index.clips)))]
            scene = clip_scene(rng, load_clip(clip), p, p, motion, "normal")
            speeds["clips", motion].append(scene.meta["speed"])
    print("| content | motion class | p10 | p50 | p90 | max (px/frame) |")
    print("|---|---|---|---|---|---|")
    for (kind, motion), values in speeds.items():
        p10, p50, p90 = np.percentile(values, [10, 50, 90])
        print(f"| {kind} | {motion} | {p10:.3f} | {p50:.3f} | {p90:.3f} | {max(values):.2f} |")


if __name__ == "__main__":
    main()
