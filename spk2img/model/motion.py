"""Motion between two images by Lucas-Kanade (Lucas & Kanade, IJCAI 1981): no weights, so it
finds motion that a network trained on few moving scenes does not learn to."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .warp import warp


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
    where the image is flat the damping keeps the flow near zero. Identical images give
    exactly zero flow.

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
