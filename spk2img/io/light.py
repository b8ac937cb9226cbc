"""The light convention (docs/format.md): linear intensity in [0, 1], 0.6 spikes/frame at I = 1."""

from __future__ import annotations

import numpy as np

SPIKE_RATE = 0.6
"""Mean spikes per frame of a pixel of intensity 1 (the camera's conversion rate)."""

DISPLAY_GAMMA = 2.2


def to_display(images: np.ndarray, gamma: float | None = DISPLAY_GAMMA) -> np.ndarray:
    """Linear intensity ``(..., H, W)`` in [0, 1] -> display ``uint8``, applying ``1/gamma``.

    ``gamma=None`` (or 1) keeps the values linear.
    """
    linear = np.clip(np.nan_to_num(images, nan=0.0), 0.0, 1.0)
    if gamma not in (None, 1, 1.0):
        linear = linear ** (1.0 / gamma)
    return np.round(linear * 255.0).astype(np.uint8)
