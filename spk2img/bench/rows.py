"""Every benchmarked method behind one interface: a small frozen dataclass per kind of method
whose :meth:`build` gives a :data:`Reconstruct` for a thread count.

Rows travel to :mod:`spk2img.bench.worker` as JSON (:func:`row_to_json`, :func:`row_from_json`),
so each is measured in a fresh process; heavy imports happen inside ``build`` only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from spk2img.runtime.self_ensemble import MIRRORS
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES

Reconstruct = Callable[[np.ndarray], np.ndarray]
"""``(FILM_FRAMES, H, W) uint8`` 0/1 window (41 frames) -> ``(H, W) float32`` linear intensity
at its centre frame; a network reads the centred crop of its own window."""

BACKENDS = {
    "torch": "PyTorch eager, fp32 (the reference)",
    "onnx": "onnxruntime, grid_sample graph, fp32",
    "onnx-deform": "onnxruntime, ONNX DeformConv graph, fp32",
    "onnx-int8": "onnxruntime, grid_sample graph, int8 weights",
    "onnx-fp16": "onnxruntime, grid_sample graph, fp16",
    "onnx-ensemble": "onnxruntime, grid_sample graph, fp32, self-ensemble (four mirrored views)",
}
"""Backend name -> what runs the network."""
CALLS_PER_FRAME = {"onnx-ensemble": len(MIRRORS)}
"""Network calls a frame takes on a backend where it is not one: its MACs are that many times
the network's."""
TRAINED_ONLY = ("onnx-ensemble",)
"""Backends that run trained weights only: the self-ensemble
(:mod:`spk2img.runtime.self_ensemble`) is four calls of the ``onnx`` row's graph, a quality
option whose time random weights would only repeat."""


@dataclass(frozen=True)
class TfpRow:
    """TFP (docs/format.md): the mean of ``window`` frames around the centre, divided by 0.6."""

    kind: ClassVar[str] = "tfp"
    window: int = FILM_FRAMES
    """Frames averaged (odd, at most the simulated window's 41)."""
    note: str = ""
    """Why this window (shown after the label)."""

    @property
    def label(self) -> str:
        return f"TFP-{self.window}" + (f" ({self.note})" if self.note else "")

    @property
    def backend(self) -> str:
        return "numpy"

    def build(self, threads: int) -> Reconstruct:
        from spk2img.runtime.classical import tfp

        return lambda spikes: tfp(spikes, [CENTER_FRAME], self.window)[0]


@dataclass(frozen=True)
class TfiRow:
    """TFI (docs/format.md): the inverse of the interval between the spikes around the centre."""

    kind: ClassVar[str] = "tfi"

    @property
    def label(self) -> str:
        return "TFI"

    @property
    def backend(self) -> str:
        return "numpy"

    def build(self, threads: int) -> Reconstruct:
        from spk2img.runtime.classical import tfi

        return lambda spikes: tfi(spikes, [CENTER_FRAME])[0]


@dataclass(frozen=True)
class NetRow:
    """One Spk2ImgNet's weights run by one backend of :data:`BACKENDS`."""

    kind: ClassVar[str] = "net"
    weights: str
    """Name of the weights: a family member with random weights, or trained ones (``shipped``)."""
    backend: str
    """A key of :data:`BACKENDS`."""
    path: str
    """The checkpoint (``torch``) or the ONNX graph (every other backend)."""
    trained: bool
    """Whether the weights were trained; untrained rows are timed but never scored."""

    @property
    def label(self) -> str:
        return f"Spk2ImgNet {self.weights}" + ("" if self.trained else " (untrained)")

    def build(self, threads: int) -> Reconstruct:
        from spk2img.evaluation.scoring import network_scorer
        from spk2img.runtime.loader import load_network

        torch = self.backend == "torch"
        network = load_network(
            None if torch else self.path,
            backend="torch" if torch else "onnx",
            checkpoint=self.path if torch else None,
            threads=threads,
            block_reuse=False,
            warm_up=False,  # the bench's own warm-up calls are timed apart
            memory_arena=True,  # as spk2img.Reconstructor (and the CLI) runs it
            self_ensemble=self.backend == "onnx-ensemble",
        )
        score = network_scorer(network.predict)
        return lambda spikes: score(spikes, None)


Row = TfpRow | TfiRow | NetRow
ROW_KINDS: dict[str, type[Row]] = {kind.kind: kind for kind in (TfpRow, TfiRow, NetRow)}


def row_to_json(row: Row) -> dict:
    """A JSON-able description of ``row``: its kind and its fields."""
    return {"kind": row.kind, **dataclasses.asdict(row)}


def row_from_json(data: dict) -> Row:
    """The row :func:`row_to_json` described."""
    fields = dict(data)
    return ROW_KINDS[fields.pop("kind")](**fields)
