"""Self-ensemble: the network on a stream and on its three mirror images, averaged.

Each view mirrors every spike frame left-right, up-down or both; the network's image of a view
is mirrored back, and the four images are averaged. The average is equivariant to those mirrors
(mirroring the stream mirrors the image, to float rounding), costs four runs of the network,
and lifts the shipped ``default`` on the real-video validation (docs/real_video.md). With
block reuse each block is encoded once per view, so streams keep their reuse. On a GPU the four
views of a call go to the network as one batch (four times the batch's memory, one launch of
each kernel instead of four); on the CPU they run one after another, so the peak memory stays
that of one call.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from spk2img.runtime.block_codec import BlockCode, BlockCodec
from spk2img.runtime.stream import Predictor

MIRRORS: tuple[tuple[int, ...], ...] = ((), (-1,), (-2,), (-2, -1))
"""The views: the axes each one flips, counted from the last (-1: width, -2: height)."""


def mirror(array: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """``array`` flipped along ``axes`` (``(..., H, W)``), contiguous for the runtime."""
    return np.ascontiguousarray(np.flip(array, axes)) if axes else array


def mean_of_views(images: Sequence[np.ndarray]) -> np.ndarray:
    """The mean of one image per view of :data:`MIRRORS`, each mirrored back first."""
    restored = [mirror(image, axes) for image, axes in zip(images, MIRRORS, strict=True)]
    return np.mean(restored, axis=0, dtype=np.float32)


class SelfEnsemblePredictor:
    """A window predictor (``(B, F, H, W)`` 0/1 -> ``(B, H, W)``) run on the four views of its
    windows: one call of ``4B`` windows when ``batch_views``, else four calls of ``B``; its
    other attributes (``geometry``, ``device`` …) are the wrapped predictor's."""

    def __init__(self, predict: Predictor, batch_views: bool = False):
        self.predict = predict
        self.batch_views = batch_views

    def __call__(self, windows: np.ndarray) -> np.ndarray:
        views = [mirror(windows, axes) for axes in MIRRORS]
        if self.batch_views:
            images = np.split(self.predict(np.concatenate(views)), len(MIRRORS))
        else:
            images = [self.predict(view) for view in views]
        return mean_of_views(images)

    def __getattr__(self, name: str):
        if name == "predict":  # not set yet (a copy being made): no recursion
            raise AttributeError(name)
        return getattr(self.predict, name)


class SelfEnsembleCodec:
    """A :class:`~spk2img.runtime.block_codec.BlockCodec` whose code of a block is the codes of
    its four views, one after another, and whose head averages the four views' images."""

    def __init__(self, codec: BlockCodec):
        self.codec = codec
        self.geometry = codec.geometry

    def encode(self, block: np.ndarray) -> BlockCode:
        """``(block_frames, H, W)`` 0/1 -> the codes of its views, concatenated."""
        return tuple(part for axes in MIRRORS for part in self.codec.encode(mirror(block, axes)))

    def head(self, codes: Sequence[BlockCode], height: int, width: int) -> np.ndarray:
        """A window's block codes (:meth:`encode`'s) -> ``(height, width)`` float32."""
        parts = len(codes[0]) // len(MIRRORS)
        views = [[code[v * parts : (v + 1) * parts] for code in codes] for v in range(len(MIRRORS))]
        return mean_of_views([self.codec.head(view, height, width) for view in views])
