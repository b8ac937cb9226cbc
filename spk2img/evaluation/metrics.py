"""Full-reference image quality: PSNR and SSIM on linear intensities with data range 1."""

from __future__ import annotations

import numpy as np

SSIM_SIGMA = 1.5
SSIM_TAPS = 11
_K1, _K2 = 0.01, 0.03


def psnr(estimate: np.ndarray, truth: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all pixels of two same-shape arrays.

    Identical inputs give ``inf``.
    """
    estimate, truth = _pair(estimate, truth)
    mse = float(np.mean((estimate - truth) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(data_range**2 / mse)


def ssim(estimate: np.ndarray, truth: np.ndarray, data_range: float = 1.0) -> float:
    """Mean structural similarity (Wang et al. 2004) of two ``(H, W)`` images.

    Gaussian window σ = 1.5 with 11 taps, K1 = 0.01, K2 = 0.03, statistics over the valid
    region only (no padding), population (not sample) covariances. A stack ``(N, H, W)`` gives
    the mean over its images. Sides shorter than 11 pixels are an error.
    """
    estimate, truth = _pair(estimate, truth)
    if estimate.ndim == 3:
        return float(
            np.mean([ssim(e, t, data_range) for e, t in zip(estimate, truth, strict=True)])
        )
    if min(estimate.shape) < SSIM_TAPS:
        raise ValueError(
            f"SSIM needs images of at least {SSIM_TAPS}x{SSIM_TAPS}, got {estimate.shape}"
        )
    c1, c2 = (_K1 * data_range) ** 2, (_K2 * data_range) ** 2
    mu_x, mu_y = _blur(estimate), _blur(truth)
    var_x = _blur(estimate * estimate) - mu_x**2
    var_y = _blur(truth * truth) - mu_y**2
    cov = _blur(estimate * truth) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return float(np.mean(num / den))


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    return a, b


def _gaussian_taps() -> np.ndarray:
    x = np.arange(SSIM_TAPS) - SSIM_TAPS // 2
    taps = np.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return taps / taps.sum()


def _blur(image: np.ndarray) -> np.ndarray:
    """Separable Gaussian filter over the valid region: ``(H-10, W-10)``."""
    taps = _gaussian_taps()
    rows = np.apply_along_axis(np.convolve, 0, image, taps, mode="valid")
    return np.apply_along_axis(np.convolve, 1, rows, taps, mode="valid")
