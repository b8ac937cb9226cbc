"""The hierarchical L1 loss of Spk2ImgNet (docs/architecture.md)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

INTERMEDIATE_WEIGHT = 0.02  # λ of the paper


def hierarchical_l1(
    image: torch.Tensor,
    estimates: torch.Tensor,
    truth: torch.Tensor,
    weight: float = INTERMEDIATE_WEIGHT,
) -> torch.Tensor:
    """``L1(image, I_k) + λ · Σ_blocks Σ_subwindows L1(estimate, I at the block's centre)``.

    Args:
        image: ``(b, 1, h, w)`` the final reconstruction (linear intensity).
        estimates: ``(b, blocks, subwindows, h, w)`` SALI's intermediate estimates.
        truth: ``(b, blocks, h, w)`` ground truth at the block centres; the middle one is ``I_k``.
    """
    key = truth.shape[1] // 2
    final = F.l1_loss(image[:, 0], truth[:, key])
    per_estimate = (estimates - truth.unsqueeze(2)).abs().mean(dim=(0, 3, 4))  # (blocks, subw)
    return final + weight * per_estimate.sum()
