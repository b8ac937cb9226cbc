"""How many stream frames to merge into each network frame on a dim stream (``binning``).

The network was trained on streams whose pixels fire up to 0.6 spikes a frame; in dim light
(a few hundredths of a spike a frame) its 41-frame window holds about one spike a pixel and
its image is mostly noise. Merging ``K`` frames into one
(:func:`~spk2img.runtime.stream.bin_frames`) makes every pixel fire about ``K`` times as often per
network frame. :func:`suggest_binning` picks ``K`` so that the stream's mean rate reaches
:data:`TARGET_RATE` while its brightest
pixels stay below saturation, within the stream's length.
"""

from __future__ import annotations

import numpy as np

from spk2img.io.light import SPIKE_RATE
from spk2img.io.spikes import as_spike_array
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.runtime.windows import MAX_BINNING

TARGET_RATE = 0.1
"""Mean spikes per pixel per network frame that binning aims at: on still held-out photos
filmed at 0.03 spikes/pixel/frame, merging 3 frames (0.09) scored best of 1 .. 5
(docs/binning.md)."""

BRIGHT_PERCENTILE = 99.5
"""The pixels whose rate must stay below saturation (``SPIKE_RATE`` a frame) once merged."""

SAMPLE_FRAMES = 400
"""Frames from the start of the stream that the firing rate is measured on."""


def firing_rates(spikes) -> np.ndarray:
    """``(H, W) float64`` spikes per frame of each pixel over the first :data:`SAMPLE_FRAMES`
    frames of a ``(T, H, W)`` 0/1 stream (an array or a memory-mapped stream)."""
    sample = as_spike_array(np.asarray(spikes[0:SAMPLE_FRAMES]))
    return sample.mean(axis=0, dtype=np.float64)


def suggest_binning(spikes, window_frames: int = PUBLISHED_GEOMETRY.window_frames) -> int:
    """The ``binning`` for a ``(T, H, W)`` 0/1 stream and a network reading ``window_frames``
    frames (its geometry's; the published 41 by default): :func:`binning_for_rates` of its
    :func:`firing_rates`."""
    return binning_for_rates(firing_rates(spikes), len(spikes), window_frames)


def binning_for_rates(
    rates: np.ndarray, n_frames: int, window_frames: int = PUBLISHED_GEOMETRY.window_frames
) -> int:
    """The ``binning`` for a stream of ``n_frames`` frames whose pixels fire ``rates`` ``(H, W)``
    spikes a frame: 1 for a normally lit one; for a dim one the ``K`` that lifts the mean rate
    to :data:`TARGET_RATE` spikes a network frame, lowered until the
    :data:`BRIGHT_PERCENTILE` th percentile pixel fires under ``SPIKE_RATE`` a frame once
    merged, and until the stream holds one window of ``window_frames * K`` frames."""
    mean, bright = float(rates.mean()), float(np.percentile(rates, BRIGHT_PERCENTILE))
    binning = int(TARGET_RATE / mean) if mean > 0 else MAX_BINNING
    if bright > 0:
        binning = min(binning, int(SPIKE_RATE / bright))
    binning = min(binning, n_frames // window_frames, MAX_BINNING)
    return max(1, binning)
