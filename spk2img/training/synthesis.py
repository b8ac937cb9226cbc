"""Training batches filmed on the training device (``spk2img train --synthesis torch``).

Worker processes only draw :class:`~spk2img.training.data.ScenePlan` s (decode and crop the
sources, draw motions, compute a clip's optical flow); :func:`film_plans` renders every scene
(:mod:`spk2img.sim.torch_render`), films it (:mod:`spk2img.sim.torch_sensor`) and augments it
on the device, in batches. The numpy simulator stays the reference
(tests/test_torch_synthesis.py compares the two).
"""

from __future__ import annotations

import numpy as np
import torch

from spk2img.model.config import Geometry
from spk2img.sim.simulator import substep_times
from spk2img.sim.torch_render import render
from spk2img.sim.torch_sensor import film

from .data import ScenePlan

SUBSTEPS = 4
"""Light samples per frame interval, as the numpy simulator's default."""


def batch_generator(seed: int, rank: int, step: int, device: torch.device) -> torch.Generator:
    """The torch generator of the sensor draws of one batch: a function of the run's seed, the
    process's rank and the step, so a resumed run films the batches it would have filmed."""
    state = np.random.SeedSequence([seed, rank, step]).generate_state(2, np.uint64)[0]
    return torch.Generator(device).manual_seed(int(state) & (2**63 - 1))


def film_plans(
    plans: list[ScenePlan], geometry: Geometry, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, F, P, P) float32`` spikes (the geometry's window) and ``(B, blocks, P, P) float32``
    ground truth at its block centres of ``plans``, on ``generator``'s device, augmented."""
    device = generator.device
    frames = geometry.window_frames
    samples = frames * SUBSTEPS  # the light's times, then the truth's (one render per scene)
    centres = np.asarray(geometry.block_centres, np.float64) + 0.5
    times = np.concatenate([substep_times(0.0, frames, SUBSTEPS), centres])
    rendered = torch.stack([render(plan.scene, times, device) for plan in plans])
    light, truth = rendered[:, :samples], rendered[:, samples:]
    b, _, h, w = light.shape
    spikes = film(light.reshape(b, frames, SUBSTEPS, h, w), [p.sensor for p in plans], generator)
    turned = [augment((s, t), plan) for s, t, plan in zip(spikes, truth, plans, strict=True)]
    return (
        torch.stack([s for s, _ in turned]).float(),
        torch.stack([t for _, t in turned]).contiguous(),
    )


def augment(pair: tuple[torch.Tensor, ...], plan: ScenePlan) -> tuple[torch.Tensor, ...]:
    """Each ``(c, h, w)`` tensor of ``pair`` turned and mirrored as ``plan`` says (as
    :func:`spk2img.training.data.augment` does to arrays)."""
    out = []
    for tensor in pair:
        tensor = torch.rot90(tensor, plan.quarter_turns, dims=(1, 2))
        out.append(torch.flip(tensor, dims=(2,)) if plan.mirror else tensor)
    return tuple(out)
