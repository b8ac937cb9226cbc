"""Reliability-weighted fusion of the aligned block features (Spk2ImgNet)."""

from __future__ import annotations

import torch
from torch import nn


class ReliabilityMask(nn.Module):
    """Per-pixel, per-channel reliability in (0, 1) of an aligned neighbour given the key:
    conv3x3 ``2c -> hidden``, PReLU, conv3x3 ``hidden -> hidden``, PReLU, conv3x3 ``-> c``,
    sigmoid, on ``[aligned, key]``.

    Args:
        channels: feature channels ``c``.
        hidden: hidden channels (``c`` as published).
    """

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(2 * channels, hidden, 3, padding=1),
            nn.PReLU(),
            nn.Conv2d(hidden, hidden, 3, padding=1),
            nn.PReLU(),
            nn.Conv2d(hidden, channels, 3, padding=1),
            nn.Sigmoid(),
        )

    def forward(self, aligned: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
        """``(b, c, h, w)`` each -> ``(b, c, h, w)``."""
        return self.body(torch.cat([aligned, key], dim=1))


class ReliabilityFusion(nn.Module):
    """Masks each aligned neighbour by its own :class:`ReliabilityMask` (one per temporal
    position, not shared), concatenates them with the key in temporal order and reconstructs:
    conv3x3 ``blocks * c -> hidden``, ReLU, conv3x3 ``-> c``, ReLU, conv3x3 ``-> out``.

    Args:
        channels: feature channels ``c``.
        blocks: temporal blocks, key included (5 as published).
        mask_hidden: hidden channels of the reliability masks.
        hidden: channels of the first reconstruction conv (192 as published).
        out_channels: output channels (1 as published; ``s * s`` for a pixel-shuffle head).
    """

    def __init__(
        self, channels: int, blocks: int, mask_hidden: int, hidden: int, out_channels: int = 1
    ) -> None:
        super().__init__()
        self.key_index = blocks // 2
        self.masks = nn.ModuleList(
            ReliabilityMask(channels, mask_hidden) for _ in range(blocks - 1)
        )
        self.reconstruct = nn.Sequential(
            nn.Conv2d(blocks * channels, hidden, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(hidden, channels, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(channels, out_channels, 3, padding=1),
        )

    def forward(self, aligned: list[torch.Tensor], key: torch.Tensor) -> torch.Tensor:
        """``aligned``: the neighbours in temporal order, ``(b, c, h, w)`` each; ``key``
        ``(b, c, h, w)`` -> ``(b, out_channels, h, w)``."""
        masked = [mask(feat, key) * feat for mask, feat in zip(self.masks, aligned, strict=True)]
        masked.insert(self.key_index, key)
        return self.reconstruct(torch.cat(masked, dim=1))  # from (b, blocks * c, h, w)
