"""Motion between two images by Lucas-Kanade (Lucas & Kanade, IJCAI 1981): no weights, so it
finds motion that a network trained on few moving scenes does not learn to."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .block_ops import per_neighbour, without_key
from .warp import warp

MOTION_DAMPING = 1e-3
"""The damping of the blocks' Lucas-Kanade systems (:func:`block_motion`; intensity in units of
SALI's estimates, about 0 .. 0.6): 1e-4 leaves on still scenes flows of 0.3 px median and
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
) -> torch.Tensor:
    """The flow that carries ``other`` onto ``key``: ``warp(other, flow) ~ key``.

    Each iteration solves, per pixel, the least-squares system of the key's gradients ``g``
    over a ``window x window`` neighbourhood, ``(sum g g^T + damping) step = sum g (key -
    warp(other, flow))``, and adds the step: a few iterations follow motion of a few pixels;
    where the image is flat the damping keeps the flow near zero. Identical images give no
    flow (to float rounding: the first step is exactly zero, the later ones resample).

    Args:
        key, other: ``(b, 1, h, w)`` intensity (about 0 .. 1).
        window: odd size of the neighbourhood, pixels.
        damping: added to the diagonal of each system (squared intensity per pixel).
        iterations: Gauss-Newton steps.

    Returns:
        ``(b, 2, h, w)``, ``(dy, dx)`` in pixels (:func:`~spk2img.model.warp.warp`'s order).
    """
    gy, gx = gradients(key)
    xx, xy, yy = window_mean(torch.cat([gx * gx, gx * gy, gy * gy], dim=1), window).unbind(1)
    xx, xy, yy = xx + damping, xy, yy + damping  # (b, h, w) each
    det = xx * yy - xy * xy
    flow = torch.zeros_like(torch.cat([key, key], dim=1))
    moved = other  # other warped by the flow so far
    for i in range(iterations):
        diff = key - moved
        bx, by = window_mean(torch.cat([gx * diff, gy * diff], dim=1), window).unbind(1)
        step = torch.stack([xx * by - xy * bx, yy * bx - xy * by], dim=1) / det.unsqueeze(1)
        flow = flow + step
        if i + 1 < iterations:
            moved = warp(other, flow)
    return flow


def block_motion(estimates: torch.Tensor, stride: int, motion_stride: int) -> torch.Tensor:
    """Each neighbour block's motion to the key block, from SALI's estimates.

    :func:`lucas_kanade` between the neighbour's intensity (the mean of its estimates) and the
    key's, both at ``1/f`` of the size (``f`` the motion stride). No gradient flows through it.

    Args:
        estimates: ``(b, blocks, n * s * s, hp / s, wp / s)``, every block in temporal order,
            folded by ``stride`` (``s``).
        stride: the estimates' fold ``s``.
        motion_stride: ``f``, a multiple of ``s``.

    Returns:
        ``(b * (blocks - 1), 2, hp / f, wp / f)``: per neighbour in order, ``(dy, dx)`` in
        pixels of ``1/f`` size such that the neighbour sampled there is the key.
    """
    blocks = estimates.shape[1]
    key = blocks // 2
    intensity = estimates.detach().mean(2, keepdim=True).flatten(0, 1)  # at 1/s
    intensity = F.avg_pool2d(intensity, motion_stride // stride).unflatten(0, (-1, blocks))
    keys = per_neighbour(intensity[:, key], blocks - 1)  # (b * neighbours, 1, hp / f, wp / f)
    others = without_key(intensity, key).flatten(0, 1)
    return lucas_kanade(keys, others, damping=MOTION_DAMPING)
