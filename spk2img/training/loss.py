"""The hierarchical loss of Spk2ImgNet (docs/architecture.md): the paper's L1, or the same with
squared errors for a last fine-tune aimed at PSNR."""

from __future__ import annotations

import torch

INTERMEDIATE_WEIGHT = 0.02  # λ of the paper
NORMS = ("l1", "l2")


def hierarchical_loss(
    image: torch.Tensor,
    estimates: torch.Tensor,
    truth: torch.Tensor,
    norm: str = "l1",
    weight: float = INTERMEDIATE_WEIGHT,
) -> torch.Tensor:
    """``E(image, I_k) + λ · Σ_blocks Σ_subwindows E(estimate, I at the block's centre)``, ``E``
    the mean absolute (``norm="l1"``, the paper's) or squared (``"l2"``) error.

    Args:
        image: ``(b, 1, h, w)`` the final reconstruction (linear intensity).
        estimates: ``(b, blocks, subwindows, h, w)`` SALI's intermediate estimates.
        truth: ``(b, blocks, h, w)`` ground truth at the block centres; the middle one is ``I_k``.
    """
    if norm not in NORMS:
        raise ValueError(f"loss {norm!r}: use one of {', '.join(NORMS)}")

    def error(difference: torch.Tensor) -> torch.Tensor:
        return difference.abs() if norm == "l1" else difference.square()

    key = truth.shape[1] // 2
    final = error(image[:, 0] - truth[:, key]).mean()
    per_estimate = error(estimates - truth.unsqueeze(2)).mean(dim=(0, 3, 4))  # (blocks, subw)
    return final + weight * per_estimate.sum()
