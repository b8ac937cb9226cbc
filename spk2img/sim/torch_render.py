"""The numpy scenes rendered in torch, on the device a model trains on.

:func:`render` gives the same intensities as a scene's own ``intensities`` (the numpy
reference): the same mirrored bilinear sampling (:func:`sample_bilinear`, the float32 steps of
:func:`spk2img.sim.scenes.sample_bilinear`), the same source coordinates (a
:class:`~spk2img.sim.scenes.MovingImage`'s ``sampling_rows`` times its ``basis``), the same
layer compositing and clip interpolation. Only the sums of the coordinate products may round
differently, so the two agree to about 1e-6 (tests/test_torch_synthesis.py).

A scene is drawn on the CPU (random crops, motions, optical flows: cheap) and only its
rendering, many samples per pixel and frame, runs here.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from spk2img.sim.natural_scenes import CLIP_MARGIN, ClipScene, LayeredScene
from spk2img.sim.scenes import MovingImage, Scene, StillScene


def mirror(c: torch.Tensor, n: int) -> torch.Tensor:
    """Fold float32 coordinates into [0, n - 1] by mirroring (period ``2 (n - 1)``)."""
    period = float(2 * (n - 1))
    c = c + float(n - 1)
    c = c - period * torch.floor(c / period)
    return torch.abs(c - float(n - 1))


def sample_bilinear(
    images: torch.Tensor, which: torch.Tensor, y: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """Bilinear samples of ``images (K, Hs, Ws) float32`` at coordinates ``y, x`` (``(N, ...)``
    float32 each), row ``i`` read from image ``which[i]`` (``(N,)`` int64); returns ``(N, ...)``
    float32. Coordinates outside an image are mirrored, as the numpy sampler does."""
    k, hs, ws = images.shape
    y, x = mirror(y, hs), mirror(x, ws)
    y0 = torch.clamp(torch.floor(y), max=float(hs - 2))
    x0 = torch.clamp(torch.floor(x), max=float(ws - 2))
    fy, fx = y - y0, x - x0
    base = (which * (hs * ws)).reshape(-1, *([1] * (y.dim() - 1)))
    i = (y0 * float(ws) + x0).long() + base
    flat = images.reshape(-1)
    top, right = flat[i], flat[i + 1]
    top = top + fx * (right - top)
    i = i + ws
    bottom, right = flat[i], flat[i + 1]
    bottom = bottom + fx * (right - bottom)
    return top + fy * (bottom - top)


@functools.singledispatch
def render(scene: Scene, times: np.ndarray, device: torch.device) -> torch.Tensor:
    """``scene``'s intensities at ``times`` (N,) as ``(N, H, W) float32`` on ``device``, the
    same as ``scene.intensities(times)`` (module doc). Scenes of other kinds are rendered by
    numpy and copied."""
    return torch.from_numpy(np.array(scene.intensities(times), np.float32)).to(device)


@render.register
def _still(scene: StillScene, times: np.ndarray, device: torch.device) -> torch.Tensor:
    image = torch.from_numpy(np.array(scene.intensity(0.0))).to(device)
    return image.expand(len(times), -1, -1)


@render.register
def _moving(scene: MovingImage, times: np.ndarray, device: torch.device) -> torch.Tensor:
    times = np.asarray(times, np.float64).ravel()
    n = len(times)
    rows = torch.from_numpy(scene.sampling_rows(times)).to(device)
    basis = torch.from_numpy(scene.basis).to(device)
    coords = rows @ basis  # (2N, H*W)
    source = torch.from_numpy(scene.source).to(device)[None]
    which = torch.zeros(n, dtype=torch.long, device=device)
    image = sample_bilinear(source, which, coords[:n], coords[n:])
    return image.reshape(n, scene.height, scene.width)


@render.register
def _layered(scene: LayeredScene, times: np.ndarray, device: torch.device) -> torch.Tensor:
    image = render(scene.background, times, device)
    for content, alpha in scene.layers:
        a = render(alpha, times, device)
        image = image + a * (render(content, times, device) - image)
    return torch.clamp(image, 0, 1)


@render.register
def _clip(scene: ClipScene, times: np.ndarray, device: torch.device) -> torch.Tensor:
    intervals, phases = scene.phases(times)
    j = torch.from_numpy(intervals).to(device)
    a = torch.from_numpy(phases).to(device)[:, None, None]
    m, h, w = CLIP_MARGIN, scene.height, scene.width
    frames = torch.from_numpy(np.ascontiguousarray(scene.frames, np.float32)).to(device)
    forward = torch.from_numpy(scene.forward[:, m : m + h, m : m + w]).to(device)[j]
    backward = torch.from_numpy(scene.backward[:, m : m + h, m : m + w]).to(device)[j]
    y = torch.arange(m, m + h, dtype=torch.float32, device=device)[:, None].expand(h, w)
    x = torch.arange(m, m + w, dtype=torch.float32, device=device)[None, :].expand(h, w)
    fwd, bwd = a[..., None] * forward, (1 - a)[..., None] * backward
    before = sample_bilinear(frames, j, y - fwd[..., 1], x - fwd[..., 0])
    after = sample_bilinear(frames, j + 1, y - bwd[..., 1], x - bwd[..., 0])
    return (1 - a) * before + a * after
