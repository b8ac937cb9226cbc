"""Compute that fits the scene: the network only where the light moves or is dim.

``quality`` picks the tier of ``method=net``:

- ``best``: the network on every pixel of every window (the default).
- ``balanced``: a cheap per-tile test on the 41-frame window (:func:`network_tiles`) marks
  the 16x16 tiles whose light moves during the window or is dim; the network runs on the
  bounding box of those tiles (plus :data:`CONTEXT` pixels of context) and TFP-41 fills the
  rest. A static, well-lit window costs a TFP; a window that moves all over costs the network.
- ``fast``: TFP-41 everywhere (the classical tier, docs/format.md).

The test compares the spike counts of the window's two halves (frames ``k-20 .. k-1`` and
``k+1 .. k+20``): a pixel whose light stays put fires as often in both, up to the sensor's
noise, while a moving edge changes its count. :data:`MOTION_THRESHOLD` is set from measurement
(``tests/test_adaptive.py`` keeps it honest): over static simulated scenes (dim, normal,
bright; ideal and real-like sensors) no 16x16 tile's mean squared count difference exceeded
0.81, while 50-85 % of the tiles of normal and bright scenes moving 0.5-3 px/frame exceeded
1.0. Dim tiles (under :data:`DIM_COUNT` spikes per pixel in 40 frames, I < 0.17) always go to
the network, where TFP is noisiest. ``spk2img bench`` reports what each tier costs and scores
on static, slow and fast scenes (``docs/bench_streaming.md``).

What the bench showed (shipped model, 250x400, 2 threads), and so the rule: on static windows
``balanced`` costs 13 ms instead of 751 ms for 3.0 dB less than ``best`` (still 1.2 dB over
TFP-41); on slow, fast and dim windows the test sends 75-100 % of the pixels to the network, so
it saves nothing and loses 0-1.0 dB where TFP fills in; on bright, slowly moving windows
(66 %) it is 16 % faster for 2.0 dB less. ``best`` therefore stays the default;
``balanced`` is for footage that is mostly still (fixed cameras), ``fast`` for previews.
"""

from __future__ import annotations

import numpy as np

from spk2img.runtime.stream import Frame, Predictor, WindowedReconstructor, tfp_image
from spk2img.runtime.windows import CenterPlan

QUALITIES = ("best", "balanced", "fast")
TILE = 16
"""Side of the tiles the test decides on (pixels)."""
MOTION_THRESHOLD = 1.0
"""A tile moves when the mean over its pixels of (count of the first half - count of the
second half)^2 is over this (spikes^2)."""
DIM_COUNT = 4.0
"""A tile is dim when its pixels fire fewer than this many spikes on average in the 40 frames
around the centre."""
CONTEXT = 16
"""Pixels of context around the network's crop (a multiple of 4, the pyramid's)."""


def check_quality(quality: str) -> str:
    from spk2img.errors import InputError

    if quality not in QUALITIES:
        raise InputError(f"unknown quality {quality!r}: choose one of {', '.join(QUALITIES)}")
    return quality


def tile_statistics(window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(41, H, W)`` 0/1 spikes -> ``(change, count)``, each ``(ceil(H / 16), ceil(W / 16))``
    float32 per tile: the mean of (spikes in the first half - spikes in the second half)^2
    (spikes^2; the centre frame in neither half) and the mean spike count of both halves."""
    half = len(window) // 2
    first = window[:half].sum(0, dtype=np.float32)
    second = window[half + 1 :].sum(0, dtype=np.float32)
    return _tile_means((first - second) ** 2), _tile_means(first + second)


def network_tiles(window: np.ndarray) -> np.ndarray:
    """``(41, H, W)`` 0/1 spikes -> ``(ceil(H / 16), ceil(W / 16))`` bool: the tiles whose light
    moves or is dim (the network's), per the module's rule."""
    change, count = tile_statistics(window)
    return (change > MOTION_THRESHOLD) | (count < DIM_COUNT)


def _tile_means(image: np.ndarray) -> np.ndarray:
    """Means of ``(H, W)`` over ``TILE x TILE`` tiles (the last row and column of tiles may be
    smaller)."""
    h, w = image.shape
    rows = np.add.reduceat(image, np.arange(0, h, TILE), axis=0)
    sums = np.add.reduceat(rows, np.arange(0, w, TILE), axis=1)
    heights = np.minimum(TILE, h - np.arange(0, h, TILE))
    widths = np.minimum(TILE, w - np.arange(0, w, TILE))
    return sums / np.outer(heights, widths)


def balanced_image(window: np.ndarray, predict: Predictor) -> tuple[np.ndarray, float]:
    """``(41, H, W)`` 0/1 spikes -> ``(H, W)`` float32 linear intensity in [0, 1] by the
    ``balanced`` rule, and the fraction of the frame's pixels the network ran on (context
    included)."""
    h, w = window.shape[1:]
    image = tfp_image(window.sum(0, dtype=np.int32), len(window))
    tiles = network_tiles(window)
    if not tiles.any():
        return image, 0.0
    rows, cols = np.nonzero(tiles.any(1))[0], np.nonzero(tiles.any(0))[0]
    y0, y1 = rows[0] * TILE, min(h, (rows[-1] + 1) * TILE)
    x0, x1 = cols[0] * TILE, min(w, (cols[-1] + 1) * TILE)
    cy0, cy1 = max(0, y0 - CONTEXT), min(h, y1 + CONTEXT)
    cx0, cx1 = max(0, x0 - CONTEXT), min(w, x1 + CONTEXT)
    crop = window[None, :, cy0:cy1, cx0:cx1].astype(np.float32)
    net = predict(crop)[0]
    image[y0:y1, x0:x1] = net[y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0]
    return image, (cy1 - cy0) * (cx1 - cx0) / (h * w)


class BalancedStream(WindowedReconstructor):
    """``quality=balanced``: each due window (the network's frames, ``plan.window``) through
    :func:`balanced_image`."""

    def __init__(self, height: int, width: int, plan: CenterPlan, predict: Predictor):
        super().__init__(height, width, plan)
        self.predict = predict
        self.network_share: list[float] = []
        """Per emitted centre, the fraction of pixels the network ran on."""

    def _due(self, k: int) -> list[Frame]:
        image, share = balanced_image(np.stack(self._frames), self.predict)
        self.network_share.append(share)
        return [(k, image)]
