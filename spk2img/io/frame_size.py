"""Whether a headerless ``.dat`` is read at its real frame size.

A ``.dat`` stores no size: any height and width whose frame (``ceil(H*W/8)`` bytes) divides the
file decode without error, and a wrong one gives noise. Read at the right size, a spike stream is
coherent in time (each pixel sees the same point of the scene frame after frame, so its spike
counts over consecutive blocks of frames agree) and in space (neighbouring pixels see
neighbouring points, so their counts agree). A wrong height shifts every frame's pixels against
the last (temporal coherence falls); a wrong width with the same pixel count puts unrelated pixels
above one another (vertical coherence falls). :func:`size_scores` measures both on the first
frames for the given size and its likely alternatives; :func:`check_frame_size` refuses a size
that another one beats clearly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img.io.spikes import SpikeFormatError, frame_nbytes, unpack_frames

SAMPLE_FRAMES = 256
"""Frames from the start of the file the coherence is measured on."""
MIN_BLOCK_FRAMES = 8
"""The shortest block of frames whose spike counts are compared with the next block's."""
BLOCK_SPIKES = 2.0
"""Blocks are long enough for this many spikes a pixel on average (dim streams: longer)."""
KNOWN_SIZES = ((250, 400), (250, 250), (1000, 1000))
"""Frame sizes of spike cameras, always among the candidates when they divide the file."""
MAX_ASPECT = 4
"""Candidates are at most this elongated (and at least 8 pixels a side)."""
MARGIN = 0.2
"""A size is refused when another scores this much more (out of 2)."""
CONFIDENT = 1.5
"""A size scoring this much or more is accepted without looking at others."""


@dataclass(frozen=True)
class SizeScore:
    """The coherence of a stream read as ``height x width`` frames."""

    height: int
    width: int
    temporal: float
    """Mean correlation of consecutive blocks' per-pixel spike counts, -1..1."""
    spatial: float
    """The lower of the horizontal and vertical neighbours' count correlations, -1..1."""

    @property
    def score(self) -> float:
        """``temporal + spatial``: 2 for a perfectly coherent stream, about 0 for noise."""
        return self.temporal + self.spatial


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    norm = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / norm if norm > 0 else 0.0


def coherence(raw: np.ndarray, height: int, width: int) -> SizeScore:
    """:class:`SizeScore` of the ``.dat`` bytes ``raw`` (at least two frames) read as
    ``height x width``, on its first :data:`SAMPLE_FRAMES` frames."""
    nbytes = frame_nbytes(height, width)
    frames = min(SAMPLE_FRAMES, raw.size // nbytes)
    spikes = unpack_frames(raw[: frames * nbytes], height, width)
    rate = max(float(spikes.mean()), 1e-6)
    block = int(np.clip(np.ceil(BLOCK_SPIKES / rate), MIN_BLOCK_FRAMES, max(1, frames // 2)))
    counts = spikes[: frames // block * block].reshape(-1, block, height, width).sum(1)
    counts = counts.astype(np.float32)
    temporal = np.mean([_correlation(a, b) for a, b in zip(counts, counts[1:], strict=False)])
    total = counts.sum(0)
    horizontal = _correlation(total[:, :-1], total[:, 1:]) if width > 1 else 0.0
    vertical = _correlation(total[:-1], total[1:]) if height > 1 else 0.0
    return SizeScore(height, width, float(temporal), min(horizontal, vertical))


def candidate_sizes(n_bytes: int, height: int, width: int) -> list[tuple[int, int]]:
    """Sizes worth comparing with ``height x width`` for a file of ``n_bytes``: the given one,
    the known camera sizes, every other shape of the same pixel count, and, for every frame size
    that divides the file into at least two :data:`MIN_BLOCK_FRAMES`-frame blocks, the shapes
    that keep the given height or the given width; all at most :data:`MAX_ASPECT` elongated."""

    def plausible(h: int, w: int) -> bool:
        fits = n_bytes % frame_nbytes(h, w) == 0
        enough = n_bytes // frame_nbytes(h, w) >= 2 * MIN_BLOCK_FRAMES
        return min(h, w) >= 8 and max(h, w) <= MAX_ASPECT * min(h, w) and fits and enough

    sizes = [(height, width), *KNOWN_SIZES]
    pixels = height * width
    sizes += [(h, pixels // h) for h in range(1, pixels + 1) if pixels % h == 0]
    frame_bytes = [f for f in range(1, int(np.sqrt(n_bytes)) + 1) if n_bytes % f == 0]
    for f in {*frame_bytes, *(n_bytes // f for f in frame_bytes)}:
        sizes += [(8 * f // width, width), (height, 8 * f // height)]
    unique = dict.fromkeys((h, w) for h, w in sizes if h > 0 and w > 0)
    return [size for size in unique if size == (height, width) or plausible(*size)]


def size_scores(path: str | Path, height: int, width: int) -> list[SizeScore]:
    """:func:`coherence` of each of :func:`candidate_sizes` for the ``.dat`` at ``path``, best
    first (the given size among them, wherever it ranks)."""
    raw = np.memmap(path, dtype=np.uint8, mode="r")
    return _ranked(raw, coherence(raw, height, width))


def _ranked(raw: np.ndarray, given: SizeScore) -> list[SizeScore]:
    """``given`` and the :func:`coherence` of every other candidate size, best first."""
    others = candidate_sizes(raw.size, given.height, given.width)[1:]  # the first is given's
    scores = [given, *(coherence(raw, h, w) for h, w in others)]
    return sorted(scores, key=lambda s: -s.score)


def check_frame_size(path: str | Path, height: int, width: int) -> None:
    """Raise :class:`SpikeFormatError` when the ``.dat`` at ``path`` read as ``height x width``
    looks like noise beside another size (:data:`MARGIN`), naming the likely sizes; a size that
    scores :data:`CONFIDENT` or more passes at once."""
    raw = np.memmap(path, dtype=np.uint8, mode="r")
    if raw.size // frame_nbytes(height, width) < 2 * MIN_BLOCK_FRAMES:
        return  # too short to judge
    given = coherence(raw, height, width)
    if given.score >= CONFIDENT:
        return
    scores = _ranked(raw, given)  # the given size is not decoded twice
    best = scores[0]
    if best.score - given.score > MARGIN:
        likely = ", ".join(f"{s.height}x{s.width} ({s.score:.2f})" for s in scores[:3])
        raise SpikeFormatError(
            f"{path}: read as {height}x{width} frames the spikes look like noise (coherence "
            f"{given.score:.2f} of 2); likely sizes: {likely}. Give the right --height/--width, "
            "or --force-size to read it as given"
        )
