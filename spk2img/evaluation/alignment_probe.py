"""Does a network's deformable alignment follow motion? A probe of its sampling offsets.

The alignment (:class:`~spk2img.model.alignment.PCDAlignment`) samples each neighbour block's
features at offsets predicted from the pair ``[neighbour, key]`` (plus, in flow-guided members,
the blocks' Lucas-Kanade motion). Under a uniform pan of ``v`` px a spike frame, the content at
the key's pixel ``x`` was at ``x + v * dt`` in a neighbour ``dt`` frames away, so an aligning
conv at a level ``scale`` px per feature pixel samples ``v * dt / scale`` away, on average over
its taps and groups. :func:`alignment_slopes` regresses each conv's mean sampling shift on that
displacement: about 1 for an alignment that follows the pan, 0 for one that samples the same
places whatever the motion (it then only fuses unaligned neighbours).
"""

from __future__ import annotations

import numpy as np
import torch

from spk2img.model.deform_conv import ModulatedDeformConv2d, recorded_mean_shifts
from spk2img.model.network import Spk2ImgNet
from spk2img.sim.scenes import Motion, MovingImage
from spk2img.sim.simulator import FILM_FRAMES, SensorConfig, simulate

PROBE_SPEEDS = (0.0, 0.14, 0.5, 1.0)
"""Pan speeds of the probe, px a spike frame along +x: still, the benchmark's, faster."""
BORDER = 2
"""Feature pixels left out at each side of the offsets' mean (the zero padding's reach), on
maps larger than four times that."""


def pan_scene(source: np.ndarray, height: int, width: int, speed: float) -> MovingImage:
    """``source`` (``(Hs, Ws)`` light in [0, 1]; larger than ``height x width`` by the pan's
    travel, else its borders are mirrored) seen through a view whose content moves straight
    along +x at ``speed`` px a spike frame, the source's centre at the output's at time 0."""
    motion = Motion(np.random.default_rng(0), height, width, 0.0, mix=(1, 0, 0, 0))
    # upright, unscaled, the view moving straight along -x: the content moves +x at ``speed``
    motion.angle0, motion.log_scale0, motion.clock = 0.0, 0.0, 1.0
    motion.velocity, motion.sway = (0.0, -speed), (0.0, 0.0)
    return MovingImage(source, height, width, motion, {"kind": "pan", "speed": speed})


def pan_spikes(source: np.ndarray, height: int, width: int, speed: float, seed: int) -> np.ndarray:
    """``(FILM_FRAMES, height, width) uint8`` spikes of :func:`pan_scene`, filmed by the
    noise-free sensor (initial charge from ``seed``)."""
    scene = pan_scene(source, height, width, speed)
    return simulate(scene, FILM_FRAMES, SensorConfig.ideal(), np.random.default_rng(seed))


def sampling_shifts(model: Spk2ImgNet, spikes: np.ndarray) -> dict[str, np.ndarray]:
    """The mean sampling offset of every deformable conv of ``model`` on one window ``(F, H, W)``
    0/1: ``{conv name: (neighbours, 2) float (dy, dx)}`` in that conv's feature pixels, over its
    taps, groups and the pixels :data:`BORDER` away from the edges, the flow that guides it
    included."""
    convs = {
        name: module
        for name, module in model.named_modules()
        if isinstance(module, ModulatedDeformConv2d)
    }
    device = next(model.parameters()).device
    with recorded_mean_shifts(convs) as recorded, torch.no_grad():
        model.eval()(torch.from_numpy(spikes[None].astype(np.float32)).to(device))
    shifts: dict[str, np.ndarray] = {}
    for name, shift in recorded.items():  # (b, 2, h, w)
        edge = BORDER if min(shift.shape[-2:]) > 4 * BORDER else 0  # small maps: all
        inner = shift[..., edge : shift.shape[-2] - edge, edge : shift.shape[-1] - edge]
        shifts[name] = inner.mean(dim=(2, 3)).double().cpu().numpy()
    return shifts


def conv_scale(model: Spk2ImgNet, name: str) -> int:
    """Full-resolution pixels per feature pixel of deformable conv ``name``."""
    level = int(name.split(".l")[-1].split(".")[0]) if ".dcn_pack.l" in name else 1
    return model.config.feature_stride * 2 ** (level - 1)


def neighbour_offsets(model: Spk2ImgNet) -> np.ndarray:
    """Frames from the key block to each neighbour block, in order (``(neighbours,)``)."""
    cfg = model.config
    steps = np.arange(cfg.num_blocks) - cfg.num_blocks // 2
    return (steps[steps != 0] * cfg.block_stride).astype(float)


def alignment_slopes(
    model: Spk2ImgNet, source: np.ndarray, height: int, width: int, speeds=PROBE_SPEEDS
) -> dict[str, float]:
    """For each deformable conv: the least-squares slope (through the origin) of its mean x
    shift, less the still pan's, on the displacement an aligning conv would sample at
    (``speed * frames / scale``), over the moving ``speeds`` and the neighbours; ``source`` as
    :func:`pan_spikes` takes it. About 1: the conv follows the motion; 0: it ignores it."""
    still, *moving = speeds
    base = sampling_shifts(model, pan_spikes(source, height, width, still, seed=0))
    frames = neighbour_offsets(model)
    ideal: dict[str, list] = {name: [] for name in base}
    found: dict[str, list] = {name: [] for name in base}
    for speed in moving:
        shifts = sampling_shifts(model, pan_spikes(source, height, width, speed, seed=0))
        for name, shift in shifts.items():
            ideal[name] += list(speed * frames / conv_scale(model, name))
            found[name] += list(shift[:, 1] - base[name][:, 1])
    return {
        name: float(np.dot(found[name], ideal[name]) / np.dot(ideal[name], ideal[name]))
        for name in base
    }
