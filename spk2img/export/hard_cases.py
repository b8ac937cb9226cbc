"""The inputs on which an exported graph must agree with PyTorch: simulated scenes and hard cases.

Every case is a batch of spike windows ``(B, 41, H, W)`` (:data:`CASE_FRAMES`) float32 0/1,
fixed by seeds, and the onnxruntime thread counts to run it with. A case may ask for a *variant* of
the network: ``far offsets`` is a copy whose offset predictors are pushed so that every deformable
tap
samples about 10**5 px outside the image (:func:`far_offset_copy`), exported the same way as the
graph under test.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from spk2img.evaluation.scoring import validation_set
from spk2img.evaluation.window_sets import seed_of
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.model.deform_conv import ModulatedDeformConv2d
from spk2img.model.network import Spk2ImgNet
from spk2img.sim.scenes import Motion, MovingImage, random_scene
from spk2img.sim.simulator import SensorConfig, simulate

HARD_CASE_SEED = seed_of("hard cases")
CASE_HEIGHT, CASE_WIDTH = 48, 64  # size of the content hard cases
CASE_FRAMES = PUBLISHED_GEOMETRY.window_frames
"""Frames of every case's windows (41): a network with a shorter window reads their centred crop
(:meth:`~spk2img.model.config.Geometry.crop`)."""
QUICK_SIZES = ((17, 23), (250, 250))
"""Scene sizes of ``spk2img verify --quick`` (CI's smoke run)."""
DEFAULT_SIZES = (*QUICK_SIZES, (250, 400))
"""Scene sizes of ``spk2img verify``: up to a spike camera's frame, within a laptop's memory."""
FULL_SIZES = (*DEFAULT_SIZES, (1000, 1000))
"""Scene sizes of ``spk2img verify --full``: 1000x1000 too (about 12 GB of peak memory)."""
FAST_SPEED = 8.0  # px/frame, well beyond the 'fast' class (0.5-3 px/frame) the net trains on
FAR_OFFSET = 1e5  # px added to every dy and subtracted from every dx in the far-offset variant
FAR_GAIN = 1e3  # the far-offset variant's offset predictors are also scaled by this


@dataclass(frozen=True)
class Case:
    """One input batch to compare torch and onnxruntime on."""

    name: str
    spikes: np.ndarray
    """``(B, 41, H, W)`` float32, 0/1."""
    threads: tuple[int, ...] = (1,)
    """onnxruntime intra-op thread counts to run it with (one result row each)."""
    variant: str | None = None
    """``None``: the network as exported; ``far offsets``: :func:`far_offset_copy` of it."""


def far_offset_copy(model: Spk2ImgNet) -> Spk2ImgNet:
    """A copy of ``model`` whose deformable convs sample far outside the image.

    The offset rows (``dy``, ``dx`` of every tap and group) of each ``conv_offset_mask`` are
    scaled by :data:`FAR_GAIN`, and :data:`FAR_OFFSET` is added to every ``dy`` bias and
    subtracted from every ``dx`` bias, so every tap lands about 10**5 px below-left of the
    image: both runtimes must read zeros there (no wrap-around, clamping, overflow or NaN).
    The mask rows are untouched.
    """
    far = copy.deepcopy(model)
    with torch.no_grad():
        for module in far.modules():
            if isinstance(module, ModulatedDeformConv2d):
                conv = module.conv_offset_mask
                n_offsets = 2 * module.kernel_size**2 * module.groups
                conv.weight[:n_offsets] *= FAR_GAIN
                conv.bias[:n_offsets] *= FAR_GAIN
                conv.bias[0:n_offsets:2] += FAR_OFFSET  # dy
                conv.bias[1:n_offsets:2] -= FAR_OFFSET  # dx
    return far.eval()


def simulated_windows(
    rng: np.random.Generator,
    height: int,
    width: int,
    motion: str = "slow",
    speed: float | None = None,
    sensor: SensorConfig | None = None,
) -> np.ndarray:
    """One simulated window ``(1, 41, H, W)`` float32 of a random scene of motion class
    ``motion`` (``speed`` px/frame overrides the class's speed) filmed by ``sensor``."""
    scene = random_scene(rng, height, width, motion, "normal")
    if speed is not None:
        motion = Motion(rng, height, width, speed)
        scene = MovingImage(scene.source, height, width, motion, scene.meta)
    spikes = simulate(scene, CASE_FRAMES, sensor or SensorConfig.real(), rng)
    return spikes[None].astype(np.float32)


def fast_stream(height: int, width: int, frames: int = 90) -> np.ndarray:
    """A ``(frames, H, W)`` uint8 stream of a fast-moving scene (real-like sensor), for
    checking the block graphs streamed with block reuse."""
    rng = np.random.default_rng([HARD_CASE_SEED, height, width])
    scene = random_scene(rng, height, width, "fast", "normal")
    return simulate(scene, frames, SensorConfig.real(), rng)


def scene_cases(per_class: int = 1) -> list[Case]:
    """The validation set's scenes (every motion x brightness class) as one batch."""
    scenes = validation_set(per_class, CASE_HEIGHT, CASE_WIDTH)
    spikes = np.stack([s.spikes for s in scenes]).astype(np.float32)
    return [Case(f"validation scenes x{len(scenes)}", spikes)]


def content_cases() -> list[Case]:
    """Inputs at the edge of what a spike camera sends, ``48x64``."""
    rng = np.random.default_rng(HARD_CASE_SEED)
    shape = (1, CASE_FRAMES, CASE_HEIGHT, CASE_WIDTH)
    single = np.zeros(shape, np.float32)
    single[0, CASE_FRAMES // 2, CASE_HEIGHT // 2, CASE_WIDTH // 2] = 1.0
    t, y, x = np.ogrid[:CASE_FRAMES, :CASE_HEIGHT, :CASE_WIDTH]
    checker = ((t + y + x) % 2).astype(np.float32)[None]  # each pixel flips every frame
    fast = simulated_windows(rng, CASE_HEIGHT, CASE_WIDTH, "fast", FAST_SPEED)
    scene = simulated_windows(rng, CASE_HEIGHT, CASE_WIDTH)
    return [
        Case("dark (all 0)", np.zeros(shape, np.float32)),
        Case("saturated (all 1)", np.ones(shape, np.float32)),
        Case("single spike", single),
        Case("checkerboard flicker", checker),
        Case(f"fast motion {FAST_SPEED:g} px/frame", fast),
        Case("far offsets (1e5 px)", scene, variant="far offsets"),
    ]


def size_cases(sizes: tuple[tuple[int, int], ...], threads: tuple[int, ...] = (1, 2)) -> list[Case]:
    """A simulated real-sensor scene at each ``(height, width)``, run with each thread count."""
    rng = np.random.default_rng([HARD_CASE_SEED, 1])
    return [Case(f"scene {h}x{w}", simulated_windows(rng, h, w), threads=threads) for h, w in sizes]


def standard_cases(sizes: tuple[tuple[int, int], ...] = DEFAULT_SIZES) -> list[Case]:
    """All cases: validation scenes, content hard cases, and a scene at each of ``sizes``
    (:data:`QUICK_SIZES`, :data:`DEFAULT_SIZES` or :data:`FULL_SIZES`)."""
    return scene_cases() + content_cases() + size_cases(sizes)


def smoke_cases(height: int, width: int) -> list[Case]:
    """The check every export ends with: a batch of two simulated windows at the example size
    and one at 17x23 (odd, not a multiple of the pyramid's)."""
    rng = np.random.default_rng([HARD_CASE_SEED, 2])
    pair = np.concatenate([simulated_windows(rng, height, width) for _ in range(2)])
    return [
        Case(f"scenes x2 {height}x{width}", pair),
        Case("scene 17x23", simulated_windows(rng, 17, 23)),
    ]
