"""No-reference quality on a real capture: TFP-41, TFI and networks reconstruct the same centres
and each method's frames are scored with NIQE (:mod:`spk2img.evaluation.niqe`; scoring needs the
``eval`` extra).

A network here is any callable that maps a ``(1, 41, H, W) float32`` window of 0/1 spikes to a
``(1, H, W) float32`` image in linear intensity (an onnxruntime session or a PyTorch module
wrapped by the caller).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from spk2img.evaluation.niqe import display_grey, niqe, niqe_corners
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.stream import net_input
from spk2img.runtime.windows import net_window

Network = Callable[[np.ndarray], np.ndarray]
"""``(1, F, H, W) float32`` spikes -> ``(1, H, W) float32`` linear intensity (``F``: the
published window, 41, which every shipped model reads)."""

WINDOW = PUBLISHED_GEOMETRY.window_frames
"""Frames of TFP's window and of the networks' windows here (41)."""


def capture_centres(frames: int, binning: int, step: int) -> list[int]:
    """Centres ``step`` frames apart, from the first to the last that holds a full window of
    the network with ``binning`` frames merged into each of its 41, in a stream of ``frames``."""
    half = net_window(WINDOW, binning) // 2
    return list(range(half, frames - half, step))


def reconstruct_at(
    spikes: np.ndarray, centers: list[int], networks: Mapping[str, Network], binning: int = 1
) -> dict[str, np.ndarray]:
    """``{method: (N, H, W) float32 linear intensity}`` at ``centers`` of ``(T, H, W)`` 0/1
    ``spikes``: ``"TFP-41"``, ``"TFI"`` and each of ``networks``, which read ``binning``
    frames merged into each of their 41 and whose output is divided by ``binning`` (back to
    the stream's intensity scale)."""
    out = {"TFP-41": tfp(spikes, centers, WINDOW), "TFI": tfi(spikes, centers, WINDOW)}
    span = net_window(WINDOW, binning)
    windows = [net_input(spikes, k, span, binning)[None].astype(np.float32) for k in centers]
    for name, network in networks.items():
        out[name] = np.concatenate([network(w) / binning for w in windows])
    return out


def niqe_scores(frames: Mapping[str, np.ndarray]) -> dict[str, dict[str, list[float]]]:
    """``{method: {"niqe": [...], "corners": [...]}}``, one score per frame of each method's
    ``(N, H, W)`` frames: NIQE of scikit-video's top-left crop
    (:func:`~spk2img.evaluation.niqe.niqe`) and the mean over the four corner crops
    (:func:`~spk2img.evaluation.niqe.niqe_corners`), on display grey levels."""
    scores = {}
    for name, stack in frames.items():
        grey = [display_grey(f) for f in stack]
        scores[name] = {
            "niqe": [niqe(g) for g in grey],
            "corners": [niqe_corners(g) for g in grey],
        }
    return scores
