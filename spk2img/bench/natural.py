"""The natural validation in the benchmark: training's held-out photographs and clips
(:mod:`spk2img.evaluation.natural_validation`), found under the folders of ``--data``, each
filmed by the noise-free sensor and by the sensor fitted to a real capture. Every scored row is
also scored there, per sensor regime: the figures that predict real-video quality, at the size
and seeds of training's validation, so they equal the model cards' and training logs'."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img.errors import InputError
from spk2img.evaluation.natural_validation import (
    HELD_OUT_CLIPS,
    HELD_OUT_PHOTOS,
    find_held_out,
    natural_validation_set,
)
from spk2img.evaluation.scoring import ValidationScene, baseline_scores

from .cases import save_spikes

NATURAL_SIZE = (96, 128)
"""Frame size of the natural validation in training (height, width)."""


@dataclass(frozen=True)
class NaturalSet:
    """The scenes (``(41, H, W) uint8`` windows with their truth, motion, brightness and
    sensor regime) and the held-out sources they were made of."""

    scenes: list[ValidationScene]
    sources: list[str]

    def save_spikes(self, directory: Path) -> Path:
        """Write the windows into ``directory`` for workers (:func:`~.cases.save_spikes`)."""
        return save_spikes(np.stack([scene.spikes for scene in self.scenes]), directory)

    def describe(self) -> dict:
        """Its count, size, sources and regimes, with the classical baselines' scores
        (``tfp_best``: TFP with the best window per scene, an oracle; ``tfi``)."""
        height, width = self.scenes[0].truth.shape
        return {
            "count": len(self.scenes),
            "height": height,
            "width": width,
            "sources": self.sources,
            "regimes": list(dict.fromkeys(scene.sensor for scene in self.scenes)),
            "baselines": baseline_scores(self.scenes),
        }


def natural_set(folders: list[Path], height: int, width: int) -> NaturalSet:
    """The natural validation at ``height x width`` from the held-out sources under
    ``folders`` (:class:`InputError` when they hold none)."""
    photos, clips = find_held_out(folders)
    if not photos and not clips:
        names = ", ".join(HELD_OUT_PHOTOS + HELD_OUT_CLIPS)
        shown = ", ".join(map(str, folders))
        raise InputError(f"--data {shown}: none of the held-out sources ({names}) is there")
    scenes = natural_validation_set(folders, height, width)
    return NaturalSet(scenes, [p.name for p in photos] + [c.name for c in clips])
