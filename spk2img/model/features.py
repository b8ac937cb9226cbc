"""Residual feature extractor of Spk2ImgNet, shared by the five temporal blocks."""

from __future__ import annotations

import torch
from torch import nn


class ResidualBlock(nn.Module):
    """``convs`` 3x3 convs with ReLUs between them, added to the input, then ReLU.

    Args:
        channels: input and output channels.
        convs: 3x3 convs in the block (3 as published).
    """

    def __init__(self, channels: int, convs: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for index in range(convs):
            if index:
                layers.append(nn.ReLU())
            layers.append(nn.Conv2d(channels, channels, 3, padding=1))
        self.body = nn.Sequential(*layers)
        self.relu = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(b, c, h, w)`` -> ``(b, c, h, w)``."""
        return self.relu(x + self.body(x))


class FeatureExtractor(nn.Module):
    """conv3x3 ``in -> channels`` + ReLU, residual blocks, and a global skip around the blocks.

    Args:
        in_channels: input channels (SALI's estimates, 4 as published).
        channels: feature channels.
        blocks: residual blocks.
        convs_per_block: 3x3 convs per residual block.
    """

    def __init__(self, in_channels: int, channels: int, blocks: int, convs_per_block: int) -> None:
        super().__init__()
        self.head = nn.Sequential(nn.Conv2d(in_channels, channels, 3, padding=1), nn.ReLU())
        self.body = nn.Sequential(
            *(ResidualBlock(channels, convs_per_block) for _ in range(blocks))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(b, in, h, w)`` -> ``(b, channels, h, w)``."""
        feat = self.head(x)
        return feat + self.body(feat)
