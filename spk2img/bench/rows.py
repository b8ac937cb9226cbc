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

from .cases import CENTER

Reconstruct = Callable[[np.ndarray], np.ndarray]
"""``(41, H, W) uint8`` 0/1 window -> ``(H, W) float32`` linear intensity at its centre frame."""

BACKENDS = {
    "torch": "PyTorch eager, fp32 (the reference)",
    "onnx": "onnxruntime, grid_sample graph, fp32",
    "onnx-deform": "onnxruntime, ONNX DeformConv graph, fp32",
    "onnx-int8": "onnxruntime, grid_sample graph, int8 weights",
    "onnx-fp16": "onnxruntime, grid_sample graph, fp16",
}
"""Backend name -> what runs the network."""


@dataclass(frozen=True)
class TfpRow:
    """TFP (docs/format.md): the mean of ``window`` frames around the centre, divided by 0.6."""

    kind: ClassVar[str] = "tfp"
    window: int = 41
    """Frames averaged (odd, at most 41)."""
    note: str = ""
    """Why this window (shown after the label)."""

    @property
    def label(self) -> str:
        return f"TFP-{self.window}" + (f" ({self.note})" if self.note else "")

    @property
    def backend(self) -> str:
        return "numpy"

    def build(self, threads: int) -> Reconstruct:
        from spk2img.core.classical import tfp

        return lambda spikes: tfp(spikes, [CENTER], self.window)[0]


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
        from spk2img.core.classical import tfi

        return lambda spikes: tfi(spikes, [CENTER])[0]


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
        if self.backend == "torch":
            from spk2img.model.predictor import TorchPredictor

            predict = TorchPredictor(self.path, threads=threads)
        else:
            from spk2img.core.onnx_backend import OnnxModel

            predict = OnnxModel(self.path, threads=threads)
        return lambda spikes: predict(spikes[None].astype(np.float32))[0]


Row = TfpRow | TfiRow | NetRow
ROW_KINDS: dict[str, type[Row]] = {kind.kind: kind for kind in (TfpRow, TfiRow, NetRow)}


def row_to_json(row: Row) -> dict:
    """A JSON-able description of ``row``: its kind and its fields."""
    return {"kind": row.kind, **dataclasses.asdict(row)}


def row_from_json(data: dict) -> Row:
    """The row :func:`row_to_json` described."""
    fields = dict(data)
    return ROW_KINDS[fields.pop("kind")](**fields)
