"""Stand-in ONNX models for tests that need a served model without a trained network."""

from __future__ import annotations

from pathlib import Path

import onnx
from onnx import TensorProto, helper

from spk2img.core.light import SPIKE_RATE
from spk2img.core.windows import NET_WINDOW

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
        [helper.make_tensor_value_info("spikes", TensorProto.FLOAT, ["B", NET_WINDOW, "H", "W"])],
        [helper.make_tensor_value_info("intensity", TensorProto.FLOAT, ["B", 1, "H", "W"])],
        initializer=[axes, rate, low, high],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    helper.set_model_props(model, TFP_MODEL_METADATA)
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path
