"""Backward warping of an image by a dense flow, with ``grid_sample`` (exports to ONNX)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def warp(x: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample ``x`` where ``flow`` points: ``out[:, :, y, x] = x[:, :, y + dy, x + dx]``,
    bilinearly, the border replicated outside the image.

    Args:
        x: ``(b, c, h, w)``.
        flow: ``(b, 2, h, w)``, ``(dy, dx)`` in pixels (the order of the deformable convs'
            offsets).

    Returns:
        ``(b, c, h, w)``.
    """
    h, w = x.shape[-2:]
    rows = torch.arange(h, dtype=x.dtype, device=x.device).view(1, -1, 1)
    cols = torch.arange(w, dtype=x.dtype, device=x.device).view(1, 1, -1)
    # grid_sample's coordinates with align_corners=False: pixel p -> (2p + 1) / size - 1
    grid = torch.stack(
        [(2 * (cols + flow[:, 1]) + 1) / w - 1, (2 * (rows + flow[:, 0]) + 1) / h - 1], dim=-1
    )  # (b, h, w, 2), x first
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
