"""Scoring a row's images: PSNR/SSIM against the ground truth (overall and per scene class),
the largest difference from a reference's images, and the best single TFP window."""

from __future__ import annotations

import numpy as np

from spk2img.evaluation.metrics import psnr
from spk2img.evaluation.scoring import TFP_WINDOWS, group_scores, image_scores, mean_scores
from spk2img.runtime.classical import tfp
from spk2img.sim.simulator import CENTER_FRAME

from .cases import SCENE_CLASSES, SENSORS, BenchSet


def quality(images: np.ndarray, cases: BenchSet) -> dict:
    """Mean PSNR (dB) and SSIM of ``images (N, H, W)`` against ``cases.truth``, over all
    windows (``psnr``, ``ssim``), per scene class (``classes[name] = {psnr, ssim}``) and per
    sensor (``sensors["ideal" | "real"] = {psnr, ssim}``: a model trained for one sensor regime
    is judged on the windows it is for)."""
    scores = image_scores(images, cases.truth)
    return {
        **mean_scores(scores),
        "classes": group_scores(scores, cases.classes, SCENE_CLASSES),
        "sensors": group_scores(scores, cases.sensors, SENSORS),
    }


def max_abs_error(images: np.ndarray, reference: np.ndarray) -> float:
    """Largest ``|images - reference|`` over all pixels (same shapes)."""
    return float(np.max(np.abs(images.astype(np.float64) - reference)))


def best_tfp_window(cases: BenchSet) -> int:
    """The one TFP window (odd, 3..41) with the highest mean PSNR over the whole set."""

    def mean_psnr(window: int) -> float:
        pairs = zip(cases.spikes, cases.truth, strict=True)
        return float(np.mean([psnr(tfp(s, [CENTER_FRAME], window)[0], t) for s, t in pairs]))

    return max(TFP_WINDOWS, key=mean_psnr)
