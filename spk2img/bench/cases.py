"""The fixed simulated benchmark set: 41-frame windows with the ground truth at their centre.

Five scene classes (static, slow and fast motion at normal light, dim and bright light with slow
motion), each filmed half by the noise-free sensor of spike-REDS and half by a real-like one
(docs/format.md). Seeds from :data:`BENCH_SEED` are disjoint from training's (``[seed, index]`` and
``[seed * 1000 + rank, index]`` with small seeds), validation's (987,654,321), the model
card's held-out test set's (123,456,789) and the int8 calibration's (161,803).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img.evaluation.window_sets import seed_of
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES, SensorConfig, ground_truth, simulate

BENCH_SEED = seed_of("bench")
SCENE_CLASSES: dict[str, tuple[str, str]] = {
    "static": ("static", "normal"),
    "slow": ("slow", "normal"),
    "fast": ("fast", "normal"),
    "dim": ("slow", "dim"),
    "bright": ("slow", "bright"),
}
"""Scene class -> (motion, brightness) of :func:`~spk2img.sim.scenes.random_scene`."""
SENSORS = {"ideal": SensorConfig.ideal(), "real": SensorConfig.real()}


@dataclass(frozen=True)
class BenchSet:
    """``spikes (N, 41, H, W) uint8`` 0/1 windows and ``truth (N, H, W) float32`` linear
    intensity at frame :data:`~spk2img.sim.simulator.CENTER_FRAME`; ``classes`` and
    ``sensors`` name each window's scene class and sensor."""

    spikes: np.ndarray
    truth: np.ndarray
    classes: list[str]
    sensors: list[str]

    def __len__(self) -> int:
        return len(self.classes)

    def save_spikes(self, directory: Path) -> Path:
        """Write the windows into ``directory`` for workers (:func:`save_spikes`)."""
        return save_spikes(self.spikes, directory)


def save_spikes(spikes: np.ndarray, directory: Path) -> Path:
    """Write ``spikes (N, 41, H, W) uint8`` to ``directory/spikes.npy``, for workers to
    memory-map (:func:`load_spikes`); the directory."""
    directory.mkdir(parents=True, exist_ok=True)
    np.save(directory / "spikes.npy", spikes)
    return directory


def load_spikes(directory: Path) -> np.ndarray:
    """The saved windows ``(N, 41, H, W) uint8``, memory-mapped (read-only)."""
    return np.load(directory / "spikes.npy", mmap_mode="r")


def benchmark_set(per_class: int, height: int, width: int) -> BenchSet:
    """``per_class`` windows of each of :data:`SCENE_CLASSES` at ``height x width``, sensors
    alternating ideal and real; deterministic."""
    spikes, truth, classes, sensors = [], [], [], []
    for i, (name, (motion, brightness)) in enumerate(SCENE_CLASSES.items()):
        for j in range(per_class):
            sensor = "ideal" if j % 2 == 0 else "real"
            rng = np.random.default_rng([BENCH_SEED, i, j])
            scene = random_scene(rng, height, width, motion, brightness)
            spikes.append(simulate(scene, FILM_FRAMES, SENSORS[sensor], rng))
            truth.append(ground_truth(scene, [CENTER_FRAME])[0])
            classes.append(name)
            sensors.append(sensor)
    return BenchSet(np.stack(spikes), np.stack(truth), classes, sensors)
