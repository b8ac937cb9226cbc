"""Motion between two images by Lucas-Kanade (Lucas & Kanade, IJCAI 1981): no weights, so it
finds motion that a network trained on few moving scenes does not learn to."""

from __future__ import annotations

from contextlib import nullcontext

import torch
import torch.nn.functional as F

from .block_ops import per_neighbour, without_key
from .warp import upsample_flow, warp

AUTOCAST_DEVICES = ("cpu", "cuda")
"""Devices with an autocast to turn off (not ``meta``, which counts the MACs)."""
MOTION_DAMPING = 1e-3
"""The constant damping of the blocks' Lucas-Kanade systems by default (:func:`block_motion`,
the config's ``motion_damping``; intensity in units of SALI's estimates, about 0 .. 0.6) in a
5 x 5 window at one level: 1e-4 leaves on still scenes flows of 0.3 px median and
0.85 px at the 90th percentile from the estimates' noise, 1e-3 a quarter of that, 1e-2 shrinks
real motion tenfold."""


def gradients(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central differences of ``(b, 1, h, w)``, the border repeated: ``(d/dy, d/dx)``, each
    ``(b, 1, h, w)``, per pixel."""
    rows = F.pad(image, (0, 0, 1, 1), mode="replicate")
    cols = F.pad(image, (1, 1, 0, 0), mode="replicate")
    return (rows[..., 2:, :] - rows[..., :-2, :]) / 2, (cols[..., 2:] - cols[..., :-2]) / 2


def window_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """The mean of ``(b, c, h, w)`` over each ``window x window`` neighbourhood (odd
    ``window``; the border repeated outside the image), ``(b, c, h, w)``.

    A depthwise convolution: onnxruntime runs it several times faster than the equal
    ``AveragePool``."""
    channels, pad = x.shape[1], window // 2
    kernel = torch.full((channels, 1, window, window), 1.0 / window**2, dtype=x.dtype)
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    return F.conv2d(padded, kernel.to(x.device), groups=channels)


def lucas_kanade(
    key: torch.Tensor,
    other: torch.Tensor,
    window: int = 5,
    damping: float = 1e-4,
    iterations: int = 3,
    damping_per_intensity: float = 0.0,
    flow: torch.Tensor | None = None,
) -> torch.Tensor:
    """The flow that carries ``other`` onto ``key``: ``warp(other, flow) ~ key``.

    Each iteration solves, per pixel, the least-squares system of the key's gradients ``g``
    over a ``window x window`` neighbourhood, ``(sum g g^T + d) step = sum g (key -
    warp(other, flow))``, and adds the step: a few iterations follow motion of a few pixels;
    where the image is flat the damping ``d`` keeps the flow near zero. ``d = damping +
    damping_per_intensity * mean(key + other) / 2`` over the neighbourhood: the second term
    grows with the light as the noise of a spike count does (Poisson), so it damps bright and
    dim scenes alike relative to their noise. Identical images give no flow (to float rounding:
    the first step from zero is exactly zero, the later ones resample).

    Args:
        key, other: ``(b, 1, h, w)`` intensity (about 0 .. 1).
        window: odd size of the neighbourhood, pixels.
        damping: added to the diagonal of each system (squared intensity per pixel).
        iterations: Gauss-Newton steps.
        damping_per_intensity: added to the diagonal per unit of the neighbourhood's mean
            intensity (intensity per pixel).
        flow: the flow to start from ``(b, 2, h, w)`` (None: zero).

    Returns:
        ``(b, 2, h, w)``, ``(dy, dx)`` in pixels (:func:`~spk2img.model.warp.warp`'s order).
    """
    gy, gx = gradients(key)
    terms = [gx * gx, gx * gy, gy * gy]
    if damping_per_intensity:
        terms.append((key + other) / 2)
    sums = window_mean(torch.cat(terms, dim=1), window).unbind(1)  # (b, h, w) each
    xx, xy, yy = sums[:3]
    diagonal = damping + (damping_per_intensity * sums[3] if damping_per_intensity else 0.0)
    xx, yy = xx + diagonal, yy + diagonal
    det = xx * yy - xy * xy
    if flow is None:
        flow, moved = torch.zeros_like(torch.cat([key, key], dim=1)), other
    else:
        moved = warp(other, flow)
    for i in range(iterations):
        diff = key - moved
        bx, by = window_mean(torch.cat([gx * diff, gy * diff], dim=1), window).unbind(1)
        step = torch.stack([xx * by - xy * bx, yy * bx - xy * by], dim=1) / det.unsqueeze(1)
        flow = flow + step
        if i + 1 < iterations:
            moved = warp(other, flow)
    return flow


def coarse_to_fine(
    key: torch.Tensor, other: torch.Tensor, levels: int = 1, **settings
) -> torch.Tensor:
    """:func:`lucas_kanade` over a pyramid of ``levels`` (each half the size of the one below,
    by 2 x 2 means): the coarsest level from zero, each finer one from the coarser flow
    upsampled and doubled, so motion ``2**(levels-1)`` times larger is followed. ``key``,
    ``other`` ``(b, 1, h, w)`` with ``h`` and ``w`` multiples of ``2**(levels-1)``; ``settings``
    as :func:`lucas_kanade` takes them -> ``(b, 2, h, w)`` ``(dy, dx)`` px."""
    keys, others = [key], [other]
    for _ in range(levels - 1):
        keys.append(F.avg_pool2d(keys[-1], 2))
        others.append(F.avg_pool2d(others[-1], 2))
    flow = None
    for level_key, level_other in zip(keys[::-1], others[::-1], strict=True):
        if flow is not None:
            flow = upsample_flow(flow)
        flow = lucas_kanade(level_key, level_other, flow=flow, **settings)
    return flow


def block_motion(
    estimates: torch.Tensor,
    stride: int,
    motion_stride: int,
    levels: int = 1,
    window: int = 5,
    damping: float = MOTION_DAMPING,
    damping_per_intensity: float = 0.0,
    iterations: int = 3,
) -> torch.Tensor:
    """Each neighbour block's motion to the key block, from SALI's estimates.

    :func:`coarse_to_fine` Lucas-Kanade between the neighbour's intensity (the mean of its
    estimates) and the key's, both at ``1/f`` of the size (``f`` the motion stride). No
    gradient flows through it.

    Args:
        estimates: ``(b, blocks, n * s * s, hp / s, wp / s)``, every block in temporal order,
            folded by ``stride`` (``s``).
        stride: the estimates' fold ``s``.
        motion_stride: ``f``, a multiple of ``s``.
        levels: the Lucas-Kanade pyramid's levels; ``hp / f`` and ``wp / f`` multiples of
            ``2**(levels-1)``.
        window, damping, damping_per_intensity, iterations: as :func:`lucas_kanade` takes
            them, at every level.

    Returns:
        ``(b * (blocks - 1), 2, hp / f, wp / f)``: per neighbour in order, ``(dy, dx)`` in
        pixels of ``1/f`` size such that the neighbour sampled there is the key; in float32,
        bf16 autocast or not (its sums of squared gradients would lose the motion in bf16).
    """
    device = estimates.device.type  # autocast off (float32 under bf16) where it exists
    off = torch.autocast(device, enabled=False) if device in AUTOCAST_DEVICES else nullcontext()
    with off:
        return _block_motion(
            estimates.detach().float(),
            stride,
            motion_stride,
            levels,
            window=window,
            damping=damping,
            damping_per_intensity=damping_per_intensity,
            iterations=iterations,
        )


def _block_motion(
    estimates: torch.Tensor, stride: int, motion_stride: int, levels: int, **settings
) -> torch.Tensor:
    blocks = estimates.shape[1]
    key = blocks // 2
    intensity = estimates.mean(2, keepdim=True).flatten(0, 1)  # at 1/s
    intensity = F.avg_pool2d(intensity, motion_stride // stride).unflatten(0, (-1, blocks))
    keys = per_neighbour(intensity[:, key], blocks - 1)  # (b * neighbours, 1, hp / f, wp / f)
    others = without_key(intensity, key).flatten(0, 1)
    return coarse_to_fine(keys, others, levels, **settings)
