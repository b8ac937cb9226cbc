"""A fixed simulated validation set and the scores of the network and the classical methods.

Scenes come from seeds no training batch uses, in every motion and brightness class, so the
scores measure scenes the network never trained on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import date
from itertools import product

import numpy as np

from spk2img.evaluation.metrics import psnr, ssim
from spk2img.evaluation.window_sets import seed_of
from spk2img.model.config import Geometry
from spk2img.runtime.classical import tfi, tfp
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES, GT_FRAMES, SensorConfig, filmed_sample

VALIDATION_SEED = seed_of("validation")
TEST_SEED = seed_of("test")
MOTIONS = ("static", "slow", "fast")
BRIGHTNESS = ("dim", "normal", "bright")
SENSORS = ("ideal", "real", "fitted")
"""Noise-free integrate-and-fire; any real-like sensor; the preset fitted to a real capture."""
TFP_WINDOWS = tuple(range(3, FILM_FRAMES + 1, 2))
"""The windows best-window TFP chooses from: every odd one up to the whole simulated window."""
KEY = GT_FRAMES.index(CENTER_FRAME)
"""The key block's index among the ground-truth block centres (2 of 5)."""


@dataclass(frozen=True)
class ValidationScene:
    spikes: np.ndarray  # (FILM_FRAMES, H, W) uint8
    truth: np.ndarray  # (H, W) float32, ground truth at the window's centre
    motion: str
    brightness: str
    sensor: str  # one of SENSORS


def validation_set(
    per_class: int = 2, height: int = 64, width: int = 96, seed: int = VALIDATION_SEED
) -> list[ValidationScene]:
    """``per_class`` scenes for each of the 9 (motion, brightness) classes.

    ``seed`` picks the set: :data:`VALIDATION_SEED` for validation during training,
    :data:`TEST_SEED` for the held-out test set of the model card.
    """
    scenes = []
    for i, (motion, light) in enumerate(product(MOTIONS, BRIGHTNESS)):
        for j in range(per_class):
            rng = np.random.default_rng([seed, i, j])
            spikes, truth, sensor = filmed_sample(rng, height, width, None, motion, light)
            kind = "ideal" if sensor == SensorConfig.ideal() else "real"
            scenes.append(ValidationScene(spikes, truth[KEY], motion, light, kind))
    return scenes


Reconstruct = Callable[[np.ndarray], np.ndarray]
"""``(FILM_FRAMES, H, W) uint8`` window -> ``(H, W)`` float32 image at its centre frame
(:data:`~spk2img.sim.simulator.CENTER_FRAME`)."""


def tfp_best_window(spikes: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """TFP with the window (odd, 3..41) that scores best against ``truth``: an oracle baseline."""
    candidates = [tfp(spikes, [CENTER_FRAME], w)[0] for w in TFP_WINDOWS]
    return max(candidates, key=lambda image: psnr(image, truth))


def tfp_window(spikes: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """TFP over the whole window (41 frames) at its centre."""
    return tfp(spikes, [CENTER_FRAME], len(spikes))[0]


def tfi_window(spikes: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """TFI at the window's centre (its spike search spans the 41 frames)."""
    return tfi(spikes, [CENTER_FRAME])[0]


def score(
    method: Callable[[np.ndarray, np.ndarray], np.ndarray], scenes: list[ValidationScene]
) -> dict:
    """:func:`score_images` of ``method``'s image of each scene."""
    return score_images([method(scene.spikes, scene.truth) for scene in scenes], scenes)


Scores = list[tuple[float, float]]
"""``(PSNR dB, SSIM)`` of each image, in order."""


def image_scores(images: Sequence[np.ndarray], truths: Sequence[np.ndarray]) -> Scores:
    """PSNR and SSIM of each ``(H, W)`` image against its truth."""
    return [(psnr(i, t), ssim(i, t)) for i, t in zip(images, truths, strict=True)]


def mean_scores(scores: Scores) -> dict[str, float]:
    """``{"psnr": mean dB, "ssim": mean}`` of ``scores``."""
    return {
        "psnr": float(np.mean([p for p, _ in scores])),
        "ssim": float(np.mean([s for _, s in scores])),
    }


def group_scores(scores: Scores, labels: Sequence[str], names: Sequence[str]) -> dict[str, dict]:
    """:func:`mean_scores` per group: ``{name: {psnr, ssim}}`` over the images labelled ``name``,
    for each of ``names`` (in that order) that labels some image."""
    grouped = {
        name: [s for s, g in zip(scores, labels, strict=True) if g == name] for name in names
    }
    return {name: mean_scores(picked) for name, picked in grouped.items() if picked}


def score_images(images: Sequence[np.ndarray], scenes: list[ValidationScene]) -> dict:
    """Mean PSNR (dB) and SSIM of ``images`` (one ``(H, W)`` image per scene, in order) against
    the scenes' truth: over all scenes (``psnr``, ``ssim``); ``psnr_<class>`` per motion,
    brightness and sensor; ``ssim_<sensor>`` per sensor."""
    scores = image_scores(images, [scene.truth for scene in scenes])
    out = mean_scores(scores)
    for attr, names in (("motion", MOTIONS), ("brightness", BRIGHTNESS), ("sensor", SENSORS)):
        labels = [getattr(scene, attr) for scene in scenes]
        for name, means in group_scores(scores, labels, names).items():
            out[f"psnr_{name}"] = means["psnr"]
            if attr == "sensor":
                out[f"ssim_{name}"] = means["ssim"]
    return out


def baseline_scores(scenes: list[ValidationScene]) -> dict[str, dict]:
    """Scores of best-window TFP and of TFI on ``scenes``."""
    return {"tfp_best": score(tfp_best_window, scenes), "tfi": score(tfi_window, scenes)}


def network_scorer(predict: Callable[[np.ndarray], np.ndarray], geometry: Geometry | None = None):
    """Adapt a batch predictor ``(B, F, H, W) -> (B, H, W)`` to :func:`score`'s method shape:
    it reads the centred ``F`` frames of each window (``geometry``: the network's; None: the one
    ``predict`` carries, else the whole window)."""
    geometry = geometry or getattr(predict, "geometry", None)
    if geometry is None:
        return lambda spikes, truth: predict(spikes[None].astype(np.float32))[0]
    return lambda spikes, truth: predict(geometry.crop(spikes)[None].astype(np.float32))[0]


def network_methods(models: str, threads: int, self_ensemble: bool = False) -> dict:
    """``{row name: method}`` (:func:`score`'s method shape) of the comma-separated ``models``,
    each a shipped model's name or ``NAME=GRAPH.onnx`` (an exported graph scored under NAME);
    ``self_ensemble``: each as its self-ensemble (four mirrored views averaged,
    :mod:`spk2img.runtime.self_ensemble`), named ``NAME, self-ensemble``."""
    from spk2img.runtime.loader import load_network

    methods = {}
    for spec in filter(None, models.split(",")):
        name, _, graph = spec.partition("=")
        network = load_network(
            graph or name, threads=threads, block_reuse=False, self_ensemble=self_ensemble
        )
        label = f"{name}, self-ensemble" if self_ensemble else name
        methods[label] = network_scorer(network.predict)
    return methods


def commands_made(earlier: str | None, command: str) -> str:
    """The commands a results file was made by, for its "Made by" line: ``earlier``'s (the
    file's previous ``command``, ``" && "``-joined, or ``None`` for a new file) then
    ``command``, each distinct command once, in the order first run. Running a command again
    re-scores the same rows in place (with the weights installed then), so the line stays one
    that remakes the file's rows in their order."""
    commands = earlier.split(" && ") if earlier else []
    return " && ".join(dict.fromkeys([*commands, command]))


def dates_made(earlier: str | None, today: date | None = None) -> str:
    """The dates a results file was made on, for its "Made by" line: ``earlier``'s (the file's
    previous ``date``, ``" and "``-joined, or ``None`` for a new file) then ``today`` (ISO
    ``YYYY-MM-DD``, default the local date), each date once, in the order first made."""
    dates = earlier.split(" and ") if earlier else []
    return " and ".join(dict.fromkeys([*dates, (today or date.today()).isoformat()]))
