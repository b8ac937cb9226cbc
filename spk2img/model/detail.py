"""Full-resolution detail for members whose fusion runs at reduced size (not in the paper)."""

from __future__ import annotations

import torch
from torch import nn

from .sali import fold, unfold


class DetailRefinement(nn.Module):
    """Adds fine detail to a prediction made at ``1/feature_stride`` size from every block's
    SALI estimates, unaligned: where the scene holds still their whole window sharpens the
    image, where it moves the key's own estimates do.

    At SALI's resolution step ``s``: conv3x3 on ``[prediction folded s x s, the blocks'
    attention-weighted SALI estimates]`` -> ``hidden``, ReLU, conv3x3 -> ``s * s``, added to the
    folded prediction and unfolded. The last conv starts at zero, so a network grown by this
    module starts out as the one it grew from.

    Args:
        estimates: channels of the blocks' weighted estimates (``blocks * n * s * s`` for ``n``
            sub-windows).
        hidden: hidden channels.
        stride: SALI's resolution step ``s``.
    """

    def __init__(self, estimates: int, hidden: int, stride: int) -> None:
        super().__init__()
        self.stride = stride
        pixels = stride**2
        self.body = nn.Sequential(
            nn.Conv2d(estimates + pixels, hidden, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(hidden, pixels, 3, padding=1),
        )
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)

    def forward(self, pred: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
        """``pred`` ``(b, 1, hp, wp)`` and the blocks' ``estimates`` ``(b, blocks, n * s * s,
        hp / s, wp / s)`` -> the refined ``(b, 1, hp, wp)``."""
        folded = fold(pred, self.stride)
        inputs = torch.cat([folded, estimates.flatten(1, 2)], dim=1)
        return unfold(folded + self.body(inputs), self.stride)
