"""Spatially adaptive light inference (SALI) of Spk2ImgNet (Zhao et al., CVPR 2021)."""

from __future__ import annotations

import torch
from torch import nn


class LightInference(nn.Module):
    """SALI: several intensity estimates of one spike block and an attention that weighs them.

    Each centred sub-window of the block (13, 11, 9 and 7 of 13 frames as published) goes through
    conv3x3 -> ``hidden`` -> ReLU -> conv3x3 -> 1, an estimate of ``0.6 * I`` that is short-window
    (sharp under motion) or long-window (quiet under low light). An attention
    (conv3x3 ``n -> attention_hidden``, ReLU, conv3x3 ``-> n``, sigmoid) scales the ``n``
    estimates per pixel.

    Args:
        block_frames: frames of the input block.
        subwindows: lengths of the centred sub-windows, each ``<= block_frames``, same parity.
        hidden: hidden channels of each sub-window branch.
        attention_hidden: hidden channels of the attention.
    """

    def __init__(
        self, block_frames: int, subwindows: tuple[int, ...], hidden: int, attention_hidden: int
    ) -> None:
        super().__init__()
        self.spans = [((block_frames - n) // 2, (block_frames + n) // 2) for n in subwindows]
        self.branches = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(n, hidden, 3, padding=1),
                nn.ReLU(),
                nn.Conv2d(hidden, 1, 3, padding=1),
            )
            for n in subwindows
        )
        self.attention = nn.Sequential(
            nn.Conv2d(len(subwindows), attention_hidden, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(attention_hidden, len(subwindows), 3, padding=1),
            nn.Sigmoid(),
        )

    def forward(self, block: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``block`` ``(b, block_frames, h, w)`` spikes -> ``(weighted, estimates)``, both
        ``(b, n, h, w)``: the attention-scaled estimates (the feature extractor's input) and the
        raw estimates of ``0.6 * I`` (what the intermediate loss sees)."""
        estimates = torch.cat(
            [
                branch(block[:, start:stop])
                for branch, (start, stop) in zip(self.branches, self.spans, strict=True)
            ],
            dim=1,
        )  # (b, n, h, w)
        return self.attention(estimates) * estimates, estimates
