import numpy as np
import pytest

from spk2img.evaluation.metrics import psnr, ssim


def _ssim_direct(x, y):
    """SSIM with an explicit 2-D Gaussian window, looping over valid positions."""
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for i in range(x.shape[0] - 10):
        for j in range(x.shape[1] - 10):
            a, b = x[i : i + 11, j : j + 11], y[i : i + 11, j : j + 11]
            ma, mb = (win * a).sum(), (win * b).sum()
            va, vb = (win * a * a).sum() - ma**2, (win * b * b).sum() - mb**2
            cov = (win * a * b).sum() - ma * mb
            vals.append(
                ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
            )
    return np.mean(vals)


def test_ssim_matches_direct_definition():
    rng = np.random.default_rng(0)
    x = rng.random((24, 30))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert ssim(y, x) == pytest.approx(_ssim_direct(y, x), abs=1e-10)
    assert ssim(x, x) == pytest.approx(1.0)
    assert ssim(y, x) == pytest.approx(ssim(x, y))
    assert ssim(np.stack([x, y]), np.stack([x, x])) == pytest.approx((1 + ssim(y, x)) / 2)


def test_psnr_values():
    x = np.zeros((10, 10))
    assert psnr(x + 0.1, x) == pytest.approx(20.0)
    assert psnr(x, x) == float("inf")
    with pytest.raises(ValueError):
        psnr(x, np.zeros((3, 3)))
