"""Classical reconstructions (docs/format.md) on whole arrays: TFP and TFI, linear [0, 1] float32.

Both run the streaming implementations of :mod:`spk2img.runtime.stream` over ``spikes`` — anything
sliceable by frames with a ``(T, H, W)`` shape (an array or a memory-mapped
:class:`~spk2img.io.spikes.DatStream`) — so arrays, files and HTTP uploads share one code path.
Results come back for the sorted, de-duplicated centres.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from spk2img.runtime.stream import TFIStream, TFPStream, collect, frame_chunks, run_stream
from spk2img.runtime.windows import CenterPlan


def tfp(spikes, centers: Sequence[int], window: int) -> np.ndarray:
    """TFP with a ``window``-frame window (odd) at each centre: ``(N, H, W) float32`` in [0, 1]."""
    plan = CenterPlan(window, centers)
    plan.centers_for(len(spikes))
    recon = TFPStream(*spikes.shape[1:], plan)
    return collect(run_stream(recon, frame_chunks(spikes)), *spikes.shape[1:])[0]


def tfi(spikes, centers: Sequence[int], window: int = 1) -> np.ndarray:
    """TFI at each centre over the whole stream: ``(N, H, W) float32`` in [0, 1].

    ``window`` only sets which centres are valid (those with a full window); the spike search
    spans the whole stream.
    """
    plan = CenterPlan(window, centers)
    plan.centers_for(len(spikes))
    recon = TFIStream(*spikes.shape[1:], plan)
    return collect(run_stream(recon, frame_chunks(spikes)), *spikes.shape[1:])[0]
