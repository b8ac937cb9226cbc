"""Reduced-precision variants of an fp32 graph, and how much they cost in accuracy.

- ``int8``: static QDQ quantisation (``onnxruntime.quantization.quantize_static``), uint8
  activations and per-channel int8 weights, ranges calibrated (min/max) on simulated windows
  from seeds disjoint from training and validation.
- ``fp16``: weights and activations in float16 (``onnxruntime.transformers.float16``), input
  and output kept float32.

Inputs and outputs keep the fp32 contract (``spikes`` float32 -> ``image`` float32 in [0, 1]);
the block encoder and head (:func:`reduce_block_graphs`) keep theirs too. fp16 is the GPU's
precision (docs/gpu.md): ``spk2img verify --fp16`` reports its error on every hard case.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.transformers.float16 import convert_float_to_float16
from onnxruntime.transformers.onnx_model import OnnxModel as TransformersOnnxModel

from spk2img.evaluation.metrics import psnr
from spk2img.evaluation.scoring import validation_set
from spk2img.evaluation.window_sets import seed_of
from spk2img.model.config import Geometry
from spk2img.runtime.onnx_backend import OnnxModel, graph_geometry
from spk2img.sim.simulator import training_sample

from .onnx_export import INPUT_NAME, check_graph, graph_props, operator_counts

PRECISIONS = ("fp32", "fp16", "int8")
CALIBRATION_SEED = seed_of("calibration")
CALIBRATION_WINDOWS = 16
CALIBRATION_SIZE = (64, 96)
MIN_PSNR_VS_FP32 = 30.0
"""A reduced-precision graph whose output is below this PSNR (dB) against the fp32 graph's on
the validation set is refused; ``verify`` holds each hard case of a reduced-precision graph to
the same PSNR against PyTorch."""


class SimulatedWindows(CalibrationDataReader):
    """``count`` simulated windows ``(1, F, H, W)`` float32 of random scenes and sensors, each
    the centred ``F`` frames of the network's ``geometry``."""

    def __init__(
        self,
        geometry: Geometry,
        count: int = CALIBRATION_WINDOWS,
        size: tuple[int, int] = CALIBRATION_SIZE,
    ):
        rng = np.random.default_rng(CALIBRATION_SEED)
        samples = [training_sample(rng, *size)[0] for _ in range(count)]
        windows = [geometry.crop(s)[None].astype(np.float32) for s in samples]
        self._feeds = iter({INPUT_NAME: w} for w in windows)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def reduce_precision(fp32_path: str | Path, out: str | Path, precision: str) -> onnx.ModelProto:
    """Write the ``precision`` (``fp16`` or ``int8``) variant of the graph at ``fp32_path`` to
    ``out``, with the fp32 graph's metadata (``precision`` updated) and its inputs and outputs
    (names, float32, dims); returns it. Any graph: the one-shot one, the block encoder, the
    head."""
    fp32 = onnx.load(fp32_path)
    metadata = graph_props(fp32)
    if precision == "fp16":
        model = convert_float_to_float16(fp32, keep_io_types=True)
        # the converter appends its input casts at the end and leaves some value_info types
        # stale: sort the nodes and let the checker's shape inference redo the types
        del model.graph.value_info[:]
        TransformersOnnxModel(model).topological_sort()
    elif precision == "int8":
        with tempfile.TemporaryDirectory(prefix="spk2img-int8-") as tmp:
            quantized = Path(tmp) / "int8.onnx"
            quantize_static(
                fp32_path,
                quantized,
                SimulatedWindows(graph_geometry(metadata, graph_io(fp32)[INPUT_NAME])),
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
            )
            model = onnx.load(quantized)
    else:
        raise ValueError(f"precision must be fp16 or int8, got {precision!r}")
    used = {domain for domain, _ in operator_counts(model)}
    kept = [o for o in model.opset_import if o.domain in used or o.domain in ("", "ai.onnx")]
    del model.opset_import[:]
    model.opset_import.extend(kept)  # the quantizer declares Microsoft domains it does not use
    onnx.helper.set_model_props(model, metadata | {"precision": precision})
    check_graph(model, graph_io(fp32))
    onnx.save_model(model, out, save_as_external_data=False)
    return model


def graph_io(model: onnx.ModelProto) -> dict[str, list[str | int]]:
    """``{name: dims}`` of a graph's inputs and outputs (a dim: its name, else its size)."""
    values = [*model.graph.input, *model.graph.output]
    return {
        v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim] for v in values
    }


def reduce_block_graphs(fp32_model: str | Path, out: str | Path, precision: str) -> list[Path]:
    """The ``precision`` variants of the block encoder and head beside the one-shot graph
    ``fp32_model``, written beside ``out`` (``OUT.encoder.onnx``, ``OUT.head.onnx``) so that
    :class:`~spk2img.runtime.block_codec.OnnxBlockCodec` finds them for ``out``; their paths."""
    from spk2img.runtime.block_codec import block_graph_paths

    sources, targets = block_graph_paths(fp32_model), block_graph_paths(out)
    for part, source in sources.items():
        reduce_precision(source, targets[part], precision)
    return list(targets.values())


def precision_report(fp32_path: str | Path, candidate_path: str | Path, per_class: int = 1) -> dict:
    """The candidate graph against the fp32 graph and against ground truth on the validation
    set (``per_class`` scenes of each motion x brightness class, 64x96).

    Returns ``max_abs_vs_fp32``, ``psnr_vs_fp32_db``, ``psnr_vs_truth_db`` (mean over scenes),
    ``fp32_psnr_vs_truth_db`` (the same for the fp32 graph), ``nonfinite`` and ``scenes``.
    """
    scenes = validation_set(per_class)
    fp32 = OnnxModel(fp32_path, threads=1)
    spikes = fp32.geometry.crop(np.stack([s.spikes for s in scenes]), axis=1).astype(np.float32)
    truth = np.stack([s.truth for s in scenes])
    reference = fp32(spikes)
    candidate = OnnxModel(candidate_path, threads=1)(spikes)
    finite = np.isfinite(candidate)
    return {
        "max_abs_vs_fp32": float(np.abs(candidate - reference).max()) if finite.all() else math.inf,
        "psnr_vs_fp32_db": psnr(candidate, reference),
        "psnr_vs_truth_db": _mean_psnr(candidate, truth),
        "fp32_psnr_vs_truth_db": _mean_psnr(reference, truth),
        "nonfinite": int((~finite).sum()),
        "scenes": len(scenes),
    }


def _mean_psnr(images: np.ndarray, truth: np.ndarray) -> float:
    """Mean over scenes of each ``(H, W)`` image's PSNR against its truth (dB)."""
    return float(np.mean([psnr(i, t) for i, t in zip(images, truth, strict=True)]))
