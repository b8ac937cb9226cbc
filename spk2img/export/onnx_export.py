"""Spk2ImgNet -> one self-contained ONNX file with dynamic batch, height and width.

The graph reads ``spikes`` ``(B, 41, H, W)`` float32 0/1 and writes ``image`` ``(B, 1, H, W)``,
linear intensity in [0, 1] (docs/format.md). Any ``H`` and ``W`` work: the network pads to its
pyramid's multiple and crops back inside the graph (:func:`spk2img.model.network.
pad_to_multiple`), with pad amounts computed from the input's shape.

The network is traced once, at a small example shape, by ``torch.onnx.export(dynamo=True)``
(tracing is shape-symbolic, so the example size does not matter; exporting the paper network at
250x400 took 13.8 GB of RAM, at 24x32 it takes well under 1 GB).
"""

from __future__ import annotations

import logging
import warnings
from collections import Counter, defaultdict
from collections.abc import Mapping
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import helper, numpy_helper
from torch import nn

from spk2img.errors import InputError
from spk2img.model.alignment import PCDAlignment
from spk2img.model.checkpoint import read_network
from spk2img.model.config import MEMBERS, Spk2ImgNetConfig
from spk2img.model.deform_conv import ModulatedDeformConv2d
from spk2img.model.detail import DetailRefinement
from spk2img.model.network import Spk2ImgNet, build_model

from .deform_conv_graph import (
    DEFORM_CONV_OPSET,
    DEFORM_CONV_TRANSLATION,
    deform_conv_as_custom_op,
)
from .metadata import model_metadata
from .sampling_ops import SAMPLING_TRANSLATION, sampling_as_custom_ops

INPUT_NAME = "spikes"
OUTPUT_NAME = "image"
GRAPHS = {"grid_sample": 18, "deform_conv": DEFORM_CONV_OPSET}
"""Graph kinds and their opsets: the deformable sampling as ``GridSample`` + 1x1 ``Conv``
(opset 18), or as ``DeformConv`` (opset 19)."""
STANDARD_DOMAINS = ("", "ai.onnx")
RANDOM_OFFSET_GAIN = 40.0
"""Gain on the default-initialised offset/mask predictors of a random network: offsets of
1-3 px on average and up to 4-6 px, masks in 0.01-0.99, on simulated scenes."""


class ExportError(RuntimeError):
    """An export that produced a graph breaking the contract (checker, domains, shapes)."""


@dataclass(frozen=True)
class ExportConfig:
    """How to export; every field has a default that works for every member."""

    graph: str = "grid_sample"
    """``grid_sample`` (opset 18) or ``deform_conv`` (opset 19, ONNX ``DeformConv``)."""
    example_batch: int = 1
    """Batch of the example input the network is traced with (the graph's batch is dynamic)."""
    example_height: int = 24
    """Height of the example input (the graph's height is dynamic)."""
    example_width: int = 32
    """Width of the example input (the graph's width is dynamic)."""

    def __post_init__(self) -> None:
        if self.graph not in GRAPHS:
            raise InputError(f"graph must be one of {', '.join(GRAPHS)}, got {self.graph!r}")

    @property
    def opset(self) -> int:
        return GRAPHS[self.graph]


@dataclass(frozen=True)
class ExportSource:
    """A network to export, in eval mode, and the ``metadata_props`` describing it."""

    model: Spk2ImgNet
    metadata: dict[str, str]


class ImageOnly(nn.Module):
    """The network's ``image`` output alone (the SALI estimates are for training). The one-shot
    graph's weights are named after it: ``model.`` and the network's state-dict key."""

    def __init__(self, model: Spk2ImgNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, spikes: torch.Tensor) -> torch.Tensor:
        """``(B, 41, H, W)`` 0/1 -> ``(B, 1, H, W)`` linear intensity in [0, 1]."""
        return self.model(spikes)[0]


def checkpoint_source(path: str | Path, name: str | None = None) -> ExportSource:
    """The network stored in a training checkpoint (its config and weights)."""
    path = Path(path)
    model, state = read_network(path)
    member = state.get("member") or next(
        (n for n, c in MEMBERS.items() if c == model.config), "custom"
    )
    source = f"{path.name}, step {state['step']}" if "step" in state else path.name
    metadata = model_metadata(model, name or f"spk2img-{member}", member, source, state)
    return ExportSource(model.eval(), metadata)


def random_source(
    member: str | Spk2ImgNetConfig, seed: int = 0, name: str | None = None
) -> ExportSource:
    """Member ``member`` (a name, or a config of its own: member ``custom``) with seeded random
    weights, for tests and benchmarks.

    Every layer gets PyTorch's default initialisation from ``torch.manual_seed(seed)``,
    including the offset/mask predictors of the deformable convs (which training starts at
    zero), scaled by :data:`RANDOM_OFFSET_GAIN`: the random network's offsets are then a few
    pixels, fractional and spatially varying, and its masks spread over (0, 1), so the exported
    graph's deformable sampling is really exercised (borders included). The detail
    refinement's last conv and the convs by which the offsets read the motion (also zero at
    the start of training) are random too.
    """
    if isinstance(member, str) and member not in MEMBERS:
        raise InputError(f"unknown member {member!r}; choose one of {', '.join(MEMBERS)}")
    generator_state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        model = build_model(member)
        for module in model.modules():
            if isinstance(module, ModulatedDeformConv2d):
                module.conv_offset_mask.reset_parameters()
                with torch.no_grad():
                    module.conv_offset_mask.weight.mul_(RANDOM_OFFSET_GAIN)
                    module.conv_offset_mask.bias.mul_(RANDOM_OFFSET_GAIN)
            elif isinstance(module, DetailRefinement):
                module.body[-1].reset_parameters()
            elif isinstance(module, PCDAlignment) and module.motion_conv is not None:
                for conv in module.motion_conv.values():
                    conv.reset_parameters()
    finally:
        torch.random.set_rng_state(generator_state)
    source = f"random weights, seed {seed}"
    label = member if isinstance(member, str) else "custom"
    metadata = model_metadata(model, name or f"spk2img-{label}-random", label, source, None)
    metadata["random_seed"] = str(seed)
    return ExportSource(model.eval(), metadata)


def weight_arrays(state_dict: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """A network's floating-point weights by the names the one-shot and block graphs give their
    initializers (``model.<state-dict key>``), as float32 arrays."""
    return {
        f"model.{key}": tensor.detach().cpu().numpy().astype(np.float32)
        for key, tensor in state_dict.items()
        if tensor.is_floating_point()
    }


def write_weights(
    model: onnx.ModelProto, old: dict[str, np.ndarray], new: dict[str, np.ndarray]
) -> set[str] | None:
    """Overwrite, in place, every float initializer of the graph ``model`` that holds a weight
    of ``old`` (:func:`weight_arrays` of the weights it was traced with) with that weight's
    value in ``new`` (same names): the graph that tracing the network with the new weights
    would give (tracing does not depend on the weights' values). A weight is found by its name,
    or, where the exporter folded it into a constant of another name (a PReLU slope reshaped
    for broadcasting), by its exact values. Returns the names of the weights written; None,
    the graph untouched, where an initializer equals several weights whose new values differ,
    or a named one does not hold its old value."""
    by_values = defaultdict(list)
    for name, array in old.items():
        by_values[array.tobytes()].append(name)
    writes, written = [], set()
    for init in model.graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT:
            continue
        held = numpy_helper.to_array(init)
        if init.name in old:
            if not np.array_equal(held.ravel(), old[init.name].ravel()):
                return None
            names = [init.name]
        else:
            names = by_values.get(np.ascontiguousarray(held).tobytes(), [])
        if not names:
            continue  # a constant of the architecture
        if len({new[name].tobytes() for name in names}) != 1:
            return None
        writes.append((init, new[names[0]].reshape(held.shape)))
        written.update(names)
    for init, array in writes:
        init.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(array), init.name))
    return written


def export_onnx(source: ExportSource, out: str | Path, config: ExportConfig) -> onnx.ModelProto:
    """Trace ``source.model``, add its metadata, check the graph, and write it to ``out``.

    Returns the written model. Raises :class:`ExportError` if the checker fails or the graph
    uses an operator outside the standard ONNX domain.
    """
    cfg = source.model.config
    frames = cfg.window_frames
    example = torch.zeros(config.example_batch, frames, *example_size(config, cfg.size_multiple))
    example[:, ::3] = 1.0  # some spikes; the values do not shape the trace
    model = trace_to_onnx(
        ImageOnly(source.model),
        (example,),
        GraphIO([INPUT_NAME], [OUTPUT_NAME], {INPUT_NAME: {0: "batch", 2: "height", 3: "width"}}),
        config,
    )
    io = one_shot_io(frames)
    name_dims(list(model.graph.output), io)  # the crop back to H x W
    return finish_graph(model, source.metadata, config, out, io)


def example_size(config: ExportConfig, multiple: int) -> tuple[int, int]:
    """``(height, width)`` of the example a network padding to ``multiple`` is traced with: the
    export config's, grown by whole multiples where the coarsest level of the padded example
    would be square or one cell wide (the exporter then ties the two sides together, or to a
    constant, and the graph fails at other sizes)."""
    cells_h, cells_w = -(-config.example_height // multiple), -(-config.example_width // multiple)
    grow_h = max(2 - cells_h, 0)
    grow_w = max(cells_h + grow_h + 1 - cells_w, 0)
    return config.example_height + grow_h * multiple, config.example_width + grow_w * multiple


@dataclass(frozen=True)
class GraphIO:
    """Names of a graph's inputs and outputs, and the dynamic axes of the inputs (in the form
    ``torch.onnx.export`` takes as ``dynamic_shapes``)."""

    inputs: list[str]
    outputs: list[str]
    dynamic_shapes: dict | tuple


def one_shot_io(window_frames: int) -> dict[str, list[str | int]]:
    """The one-shot graph's I/O contract for a network reading ``window_frames`` frames: names
    and dims (symbolic names or sizes), in order."""
    return {
        INPUT_NAME: ["batch", window_frames, "height", "width"],
        OUTPUT_NAME: ["batch", 1, "height", "width"],
    }


def trace_to_onnx(
    module: nn.Module, examples: tuple[torch.Tensor, ...], io: GraphIO, config: ExportConfig
) -> onnx.ModelProto:
    """Trace ``module`` (eval mode) on ``examples`` with ``torch.onnx.export(dynamo=True)`` at
    ``config``'s graph kind and opset; the deformable convs become ``DeformConv`` nodes for the
    ``deform_conv`` kind; the bilinear samples and upsamplings are traced as one op each
    (:mod:`spk2img.export.sampling_ops`)."""
    deform_conv = config.graph == "deform_conv"
    registration_log = logging.getLogger("torch.onnx._internal.exporter._registration")
    previous_level = registration_log.level
    registration_log.setLevel(logging.ERROR)  # "torchvision is not installed" is expected
    try:
        with (
            torch.no_grad(),
            sampling_as_custom_ops(),
            deform_conv_as_custom_op() if deform_conv else nullcontext(),
            warnings.catch_warnings(),
        ):
            # raised inside torch.export by torch's own pytree code, not actionable here
            warnings.filterwarnings("ignore", ".*LeafSpec.*", FutureWarning)
            # derived dims (the head's 2*h, 4*h) are named after their root: nothing lost
            warnings.filterwarnings("ignore", ".*shares the same shape constraints.*")
            program = torch.onnx.export(
                module.eval(),
                examples,
                dynamo=True,
                opset_version=config.opset,
                input_names=io.inputs,
                output_names=io.outputs,
                dynamic_shapes=io.dynamic_shapes,
                custom_translation_table=SAMPLING_TRANSLATION
                | (DEFORM_CONV_TRANSLATION if deform_conv else {}),
                external_data=False,
                optimize=True,
                verbose=False,
            )
    finally:
        registration_log.setLevel(previous_level)
    return program.model_proto


def name_dims(values: list[onnx.ValueInfoProto], expected: dict[str, list[str | int]]) -> None:
    """Give the symbolic dims of ``values`` the names of ``expected``. The exporter's are
    expressions of the input's, such as ``4*ceil(s1/4)`` or, after a crop back to the input's
    size, ``Min(height, 2*((height + ...)//2))``; named, the graph documents its contract (the
    parity checks run it at many sizes)."""
    for value in values:
        for dim, want in zip(value.type.tensor_type.shape.dim, expected[value.name], strict=True):
            if isinstance(want, str):
                dim.dim_param = want


def finish_graph(
    model: onnx.ModelProto,
    metadata: dict[str, str],
    config: ExportConfig,
    out: str | Path,
    expected_io: dict[str, list[str | int]],
) -> onnx.ModelProto:
    """Add ``metadata`` (and the graph kind and opset) to ``model``, :func:`check_graph` it
    against ``expected_io`` and write it to ``out``; returns it."""
    out = Path(out)
    helper.set_model_props(model, {**metadata, "graph": config.graph, "opset": str(config.opset)})
    check_graph(model, expected_io)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, out, save_as_external_data=False)
    return model


def operator_counts(model: onnx.ModelProto) -> Counter[tuple[str, str]]:
    """``(domain, op_type)`` -> number of nodes, over the main graph and its local functions."""
    nodes = list(model.graph.node) + [n for f in model.functions for n in f.node]
    return Counter((node.domain, node.op_type) for node in nodes)


def check_graph(model: onnx.ModelProto, expected_io: dict[str, list[str | int]]) -> None:
    """Raise :class:`ExportError` unless ``model`` passes ``onnx.checker`` (full check, with
    shape inference), uses standard-domain operators only, and has the I/O contract
    ``expected_io`` (:func:`one_shot_io` for the one-shot graph)."""
    try:
        onnx.checker.check_model(model, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ExportError(f"the exported graph fails onnx.checker: {exc}") from exc
    counts = operator_counts(model)
    foreign = sorted({f"{d}::{op}" for d, op in counts if d not in STANDARD_DOMAINS})
    if foreign:
        raise ExportError(f"the exported graph uses non-standard operators: {', '.join(foreign)}")
    io = graph_io(model)
    if io != expected_io:
        raise ExportError(f"unexpected graph I/O: {io}, expected {expected_io}")


def graph_io(model: onnx.ModelProto) -> dict[str, list[str | int]]:
    """A graph's inputs and outputs in order: name -> dims (symbolic names or sizes)."""
    return {v.name: _dims(v) for v in [*model.graph.input, *model.graph.output]}


def graph_props(model: onnx.ModelProto) -> dict[str, str]:
    """A graph's ``metadata_props`` as a dict."""
    return {prop.key: prop.value for prop in model.metadata_props}


def graph_kind(model: onnx.ModelProto) -> str:
    """``deform_conv`` if the graph samples with ``DeformConv`` nodes, else ``grid_sample``."""
    return "deform_conv" if ("", "DeformConv") in operator_counts(model) else "grid_sample"


def _dims(value: onnx.ValueInfoProto) -> list[str | int]:
    return [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]
