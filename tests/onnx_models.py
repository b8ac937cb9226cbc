"""ONNX models for tests: a stand-in for a served model without a trained network, and a tiny
Spk2ImgNet checkpoint exported through the pipeline the CLI uses."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import onnx
from onnx import TensorProto, helper

from spk2img.io.light import SPIKE_RATE
from spk2img.model.config import MEMBERS

TINY_TRAIN_COMMIT = "0123456789abcdef0123456789abcdef01234567"
"""The training commit recorded in :func:`write_tiny_checkpoint`'s checkpoint."""
EXPORT_EXAMPLE_SIZE = 16
"""Side of the example window the test exports trace at (``1x41x16x16``)."""

THREE_BLOCKS = replace(MEMBERS["tiny"], num_blocks=3, sali_subwindows=(13, 7), residual_blocks=1)
"""``tiny`` with three blocks, a 27-frame window (``k-13 .. k+13``), cut to the least that
still has every component (two SALI sub-windows, one residual block, ``tiny``'s two-level
alignment pyramid with its upsampling between levels): the network of the export tests, whose
graphs export in less time than ``tiny``'s, in a geometry other than the published one. The
published geometry's graphs are the shipped models' (test_shipped_model.py), as are the folded
``cpu``'s checks off its size multiple."""

TFP_MODEL_METADATA = {"name": "tfp41-standin", "version": "0", "kind": "test stand-in"}


def write_tfp41_model(path: Path) -> Path:
    """Write a valid reconstruction graph that is exactly TFP with a 41-frame window.

    ``spikes`` ``(B, 41, H, W)`` float32 -> ReduceMean over axis 1 -> ÷ 0.6 -> Clip [0, 1] ->
    ``(B, 1, H, W)``, with dynamic B, H and W and some ``metadata_props``.
    """
    axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
    rate = helper.make_tensor("rate", TensorProto.FLOAT, [], [SPIKE_RATE])
    low = helper.make_tensor("low", TensorProto.FLOAT, [], [0.0])
    high = helper.make_tensor("high", TensorProto.FLOAT, [], [1.0])
    nodes = [
        helper.make_node("ReduceMean", ["spikes", "axes"], ["mean"], keepdims=1),
        helper.make_node("Div", ["mean", "rate"], ["linear"]),
        helper.make_node("Clip", ["linear", "low", "high"], ["intensity"]),
    ]
    graph = helper.make_graph(
        nodes,
        "tfp41",
        [helper.make_tensor_value_info("spikes", TensorProto.FLOAT, ["B", 41, "H", "W"])],
        [helper.make_tensor_value_info("intensity", TensorProto.FLOAT, ["B", 1, "H", "W"])],
        initializer=[axes, rate, low, high],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    helper.set_model_props(model, TFP_MODEL_METADATA)
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def write_tiny_checkpoint(path: Path, config=None, seed: int = 3) -> Path:
    """A ``tiny`` checkpoint (or one of ``config``, member ``custom``) trained for 0 steps, with
    the random (non-zero) offset predictors of :func:`~spk2img.export.onnx_export.random_source`
    so that the deformable sampling moves. A random network's image can be 0 everywhere (clipped
    below): ``seed`` picks one whose image is not, so that comparisons of its outputs compare."""
    from spk2img.export.onnx_export import random_source
    from spk2img.model.checkpoint import config_to_dict, save_checkpoint

    model = random_source(config or "tiny", seed=seed).model
    save_checkpoint(
        path,
        model=model.state_dict(),
        config=config_to_dict(model.config),
        member="tiny" if config is None else "custom",
        step=0,
        commit=TINY_TRAIN_COMMIT,
    )
    return path


def write_tiny_export(checkpoint: Path, out: Path) -> Path:
    """``checkpoint`` exported (grid_sample graph, block graphs beside it) and verified."""
    from spk2img.export.onnx_export import ExportConfig, checkpoint_source
    from spk2img.export.pipeline import export_verified

    example = ExportConfig(example_height=EXPORT_EXAMPLE_SIZE, example_width=EXPORT_EXAMPLE_SIZE)
    result = export_verified(checkpoint_source(checkpoint), out, example)
    assert result.parity.passed and result.precision is None
    return out
