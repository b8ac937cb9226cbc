"""Streaming the network with every 13-frame block encoded once (block-feature reuse).

The window of centre ``k`` is the network's blocks starting at ``k + s`` for each of its
geometry's :attr:`~spk2img.model.config.Geometry.block_starts` ``s`` (as published, five blocks at
``k - 20 + 7 i``, ``i = 0 .. 4``; centres ``k`` and ``k + 7`` share four of them).
:class:`BlockReuseStream` encodes a block as soon as its last frame arrives (when some requested
centre needs it), keeps the codes of the blocks a later centre still needs, and runs only the
align-and-fuse head per centre. Outputs equal the
one-shot network's to float rounding.
"""

from __future__ import annotations

import numpy as np

from spk2img.runtime.block_codec import BlockCode, BlockCodec
from spk2img.runtime.stream import Frame, WindowedReconstructor
from spk2img.runtime.windows import CenterPlan, WindowError


def reuses_blocks(plan: CenterPlan, codec: BlockCodec) -> bool:
    """Whether ``plan``'s centres share blocks: they all lie on one grid of ``block_stride``
    frames (a stride that is a multiple of 7, or such a list of centres) and some two are less
    than a window apart. Then at most ``num_blocks`` codes are held at once."""
    step = codec.geometry.block_stride
    span = step * codec.geometry.num_blocks  # centres this far apart share no block
    if plan.stride is not None:
        return plan.stride % step == 0 and plan.stride < span
    gaps = np.diff(plan.centers)
    return bool(gaps.size) and bool(np.all(gaps % step == 0)) and bool(gaps.min() < span)


class BlockReuseStream(WindowedReconstructor):
    """The network through a :class:`BlockCodec`, each needed block encoded once.

    Memory: the last window of frames and the codes of the blocks a centre not yet emitted reads (at
    most ``num_blocks`` codes when the centres lie on a grid of ``block_stride``).
    """

    def __init__(self, height: int, width: int, plan: CenterPlan, codec: BlockCodec):
        geometry = codec.geometry
        if plan.window != geometry.window_frames:
            raise WindowError(
                f"the network needs a {geometry.window_frames}-frame window, got {plan.window}"
            )
        super().__init__(height, width, plan)
        self.codec = codec
        self.block_frames = geometry.block_frames
        self.starts = geometry.block_starts
        """Block starts relative to the centre (-20, -13, -6, 1, 8 as published)."""
        self._codes: dict[int, BlockCode] = {}
        self.blocks_encoded = 0

    @property
    def codes_held(self) -> int:
        """Block codes held now."""
        return len(self._codes)

    def _slide(self, entering: np.ndarray, leaving: np.ndarray | None) -> None:
        # the frame just appended is frame ``frames_seen`` (counted after this call)
        start = self.frames_seen - self.block_frames + 1
        if start >= 0 and any(self.plan.wants(start - offset) for offset in self.starts):
            block = np.stack(list(self._frames)[-self.block_frames :])
            self._codes[start] = self.codec.encode(block.astype(np.float32))
            self.blocks_encoded += 1

    def _due(self, k: int) -> list[Frame]:
        image = self.codec.head([self._codes[k + s] for s in self.starts], self.height, self.width)
        for start in [s for s in self._codes if not self._needed_after(s, k)]:
            del self._codes[start]
        return [(k, image)]

    def _needed_after(self, start: int, k: int) -> bool:
        """Whether a requested centre after ``k`` reads the block at ``start``."""
        return any(start - s > k and self.plan.wants(start - s) for s in self.starts)

    def _finish(self) -> list[Frame]:
        self._codes.clear()  # the blocks of centres the stream ended too early for
        return []
