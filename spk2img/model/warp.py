"""Backward warping of an image by a dense flow, with ``grid_sample`` (exports to ONNX)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sampling_grid(rows: torch.Tensor, cols: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Sampling positions in pixels of an ``h x w`` input (``rows``, ``cols``, the same shape)
    -> ``grid_sample``'s grid (``align_corners=False``: pixel ``p`` at ``(2p + 1) / size - 1``),
    that shape plus a last dimension of 2, x first."""
    return torch.stack([(2 * cols + 1) / w - 1, (2 * rows + 1) / h - 1], dim=-1)


def upsample_flow(flow: torch.Tensor, factor: int = 2) -> torch.Tensor:
    """Displacements ``(b, 2k, h, w)`` in pixels of one resolution -> the same motion at
    ``factor`` times it, ``(b, 2k, h * factor, w * factor)``: bilinearly upsampled, each
    displacement times ``factor`` (a coarse pyramid level's flow or offsets, read at the finer
    level)."""
    return factor * F.interpolate(flow, scale_factor=factor, mode="bilinear", align_corners=False)


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
    # positions in float32 at least (bf16 autocast would round 37.3 px to 37.25), sampled from
    # an input as wide
    exact = torch.promote_types(x.dtype, torch.float32)
    rows = torch.arange(h, dtype=exact, device=x.device).view(1, -1, 1)
    cols = torch.arange(w, dtype=exact, device=x.device).view(1, 1, -1)
    flow = flow.to(exact)
    grid = sampling_grid(rows + flow[:, 0], cols + flow[:, 1], h, w)  # (b, h, w, 2)
    return F.grid_sample(
        x.to(exact), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
