"""The hierarchical loss of Spk2ImgNet (docs/architecture.md): the paper's L1, or with the final
image scored by PSNR, the validation's own measure, for a last fine-tune."""

from __future__ import annotations

import torch

from .config import check_final_term

INTERMEDIATE_WEIGHT = 0.02  # λ of the paper
PSNR_FLOOR_MSE = 1e-6
"""Added to each window's squared error before the logarithm: PSNR saturates at 60 dB."""


def hierarchical_loss(
    image: torch.Tensor,
    estimates: torch.Tensor,
    truth: torch.Tensor,
    final: str = "l1",
    weight: float = INTERMEDIATE_WEIGHT,
) -> torch.Tensor:
    """``E(image, I_k) + λ · Σ_blocks Σ_subwindows L1(estimate, I at the block's centre)``.

    ``E`` is the mean absolute error (``final="l1"``, the paper's) or minus the mean PSNR (dB)
    of the batch's windows, ``10 · log10(MSE + 1e-6)`` averaged over them (``"psnr"``), which
    weighs each window's error relative to its own size, as a mean PSNR does.

    Args:
        image: ``(b, 1, h, w)`` the final reconstruction (linear intensity).
        estimates: ``(b, blocks, subwindows, h, w)`` SALI's intermediate estimates.
        truth: ``(b, blocks, h, w)`` ground truth at the block centres; the middle one is ``I_k``.
    """
    check_final_term(final)
    key = truth.shape[1] // 2
    difference = image[:, 0] - truth[:, key]
    if final == "l1":
        final_term = difference.abs().mean()
    else:
        mse = difference.square().mean(dim=(1, 2))
        final_term = 10 * torch.log10(mse + PSNR_FLOOR_MSE).mean()
    per_estimate = (estimates - truth.unsqueeze(2)).abs().mean(dim=(0, 3, 4))  # (blocks, subw)
    return final_term + weight * per_estimate.sum()
