"""The network as two ONNX graphs for streams: a block encoder and an align-and-fuse head.

Consecutive outputs share most of their input: the windows of centres ``k`` and ``k + 7`` share
four of their five 13-frame blocks. Exported this way, a streaming runtime
(:class:`spk2img.runtime.block_stream.BlockReuseStream`) encodes each block once and keeps the
codes of the blocks still needed, instead of re-running SALI and the feature extractor on every
block of every output.

**Encoder** ``<stem>.encoder.onnx``: input ``block`` ``(B, 13, H, W)`` float32 0/1; outputs, for
each pyramid level ``l = 1 .. L`` (sizes ``hp / (s * 2**(l-1))``, ``wp / (s * 2**(l-1))`` where
``s`` is the feature stride and ``hp``, ``wp`` are ``H``, ``W`` padded to ``s * 2**(L-1)``;
:mod:`spk2img.model.block_split` builds both parts):

- ``feat_l{l}`` ``(B, c, h_l, w_l)``: the block's feature pyramid;
- ``nbr_l{l}`` and ``key_l{l}`` ``(B, c, h_l, w_l)``: its terms of level ``l``'s first offset
  conv as a neighbour and as the key (that conv is linear in ``[neighbour, key]``).

**Head** ``<stem>.head.onnx``: inputs ``feat_l{l}`` ``(B, 5, c, h_l, w_l)`` (the five blocks in
temporal order), ``nbr_l{l}`` ``(B, 4, c, h_l, w_l)`` (the four neighbours in order) and
``key_l{l}`` ``(B, c, h_l, w_l)`` (the key block's); output ``image`` ``(B, 1, hp, wp)``
(dims ``padded_height``, ``padded_width``), linear
intensity in [0, 1], still padded: crop it to ``H x W``.

Both carry the one-shot graph's metadata (same ``weights_sha256``) plus ``part``
(``encoder`` / ``head``). Encoder then head equals the one-shot graph to float rounding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.export import Dim

from spk2img.model.block_code import DETAIL_CODE, code_role, role_blocks
from spk2img.model.block_split import AlignFuseHead, BlockEncoder, model_code_names, repeated_code
from spk2img.model.network import Spk2ImgNet
from spk2img.runtime.block_codec import OnnxBlockCodec, block_graph_paths
from spk2img.runtime.block_stream import BlockReuseStream
from spk2img.runtime.stream import collect, frame_chunks, net_input, run_stream
from spk2img.runtime.windows import CenterPlan

from .onnx_export import (
    ExportConfig,
    ExportSource,
    GraphIO,
    example_size,
    finish_graph,
    name_dims,
    trace_to_onnx,
)

BLOCK_INPUT = "block"
IMAGE_OUTPUT = "image"


def export_block_graphs(
    source: ExportSource, out: str | Path, config: ExportConfig
) -> dict[str, Path]:
    """Write the encoder and head of ``source`` beside the one-shot graph ``out``
    (``<stem>.encoder.onnx``, ``<stem>.head.onnx``); returns ``{part: path}``."""
    model = source.model.eval()
    cfg = model.config
    names = model_code_names(model)
    stacked = role_blocks(cfg.num_blocks)  # blocks each role stacks in the head's inputs
    roles = [code_role(name) for name in names]
    paths = block_graph_paths(out)
    # (batch, channels, height, width) of each code, and how many times the padded size over
    # the size multiple (the coarsest level's size, or less where the motion's pyramid pads
    # further) its own size is
    code_dims, scales = {}, {}
    for name, role in zip(names, roles, strict=True):
        if role == DETAIL_CODE:  # the SALI estimates, at the SALI stride
            estimates = len(cfg.sali_subwindows) * cfg.sali_stride**2
            code_dims[name] = ["batch", estimates, "h_sali", "w_sali"]
            scales[name] = cfg.size_multiple // cfg.sali_stride
        else:  # level l is at 1 / (feature stride * 2**(l-1)) of the padded size
            code_dims[name] = ["batch", cfg.channels, f"h_{name[-2:]}", f"w_{name[-2:]}"]
            scales[name] = cfg.size_multiple // (cfg.feature_stride * 2 ** (int(name[-1]) - 1))

    block = torch.zeros(
        config.example_batch, cfg.block_frames, *example_size(config, cfg.size_multiple)
    )
    block[:, ::3] = 1.0  # some spikes; the values do not shape the trace
    encoder_io = GraphIO([BLOCK_INPUT], names, {BLOCK_INPUT: {0: "batch", 2: "height", 3: "width"}})
    encoder = trace_to_onnx(BlockEncoder(model), (block,), encoder_io, config)
    encoder_expected = {BLOCK_INPUT: ["batch", cfg.block_frames, "height", "width"], **code_dims}
    name_dims(list(encoder.graph.output), encoder_expected)
    encoder_meta = {**source.metadata, "part": "encoder"}
    finish_graph(encoder, encoder_meta, config, paths["encoder"], encoder_expected)

    # the head takes every block's pyramid, the neighbours' terms and the key's terms (and SALI
    # estimates)
    with torch.no_grad():
        examples = repeated_code(BlockEncoder(model)(block), names, cfg.num_blocks)
    batch, coarse_h, coarse_w = Dim("batch"), Dim("coarse_height"), Dim("coarse_width")
    shapes = []
    for name, role in zip(names, roles, strict=True):
        first = 2 if stacked[role] is None else 3  # the spatial axes
        scale = scales[name]
        shapes.append({0: batch, first: scale * coarse_h, first + 1: scale * coarse_w})
    head_io = GraphIO(names, [IMAGE_OUTPUT], (tuple(shapes),))
    head = trace_to_onnx(AlignFuseHead(model), examples, head_io, config)
    head_expected = {
        name: [dims[0], *([] if stacked[role] is None else [stacked[role]]), *dims[1:]]
        for (name, dims), role in zip(code_dims.items(), roles, strict=True)
    } | {IMAGE_OUTPUT: ["batch", 1, "padded_height", "padded_width"]}
    name_dims([*head.graph.input, *head.graph.output], head_expected)
    finish_graph(head, {**source.metadata, "part": "head"}, config, paths["head"], head_expected)
    return paths


def block_parity(
    model_path: str | Path,
    model: Spk2ImgNet,
    height: int = 17,
    width: int = 23,
    frames: int = 76,
    seed: int = 0,
) -> float:
    """Largest difference between the block graphs beside ``model_path``, streamed with block
    reuse at the block stride over a random ``(frames, height, width)`` stream, and ``model`` run in
    PyTorch on each window at once (linear intensity units)."""
    spikes = (np.random.default_rng(seed).random((frames, height, width)) < 0.3).astype(np.uint8)
    streamed, centers, _ = stream_block_graphs(model_path, spikes)
    return float(np.abs(streamed - whole_windows(model, spikes, centers)).max())


def stream_block_graphs(
    model_path: str | Path, spikes: np.ndarray, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray, str]:
    """``(T, H, W)`` spikes streamed through the block graphs beside ``model_path`` (one
    onnxruntime thread on ``device``) at every ``block_stride``-th centre of their geometry, each
    block encoded once: ``frames (N, H, W)``, ``centers (N,)`` and the device they ran on."""
    height, width = spikes.shape[1:]
    codec = OnnxBlockCodec(model_path, threads=1, device=device)
    geometry = codec.geometry
    plan = CenterPlan(geometry.window_frames, stride=geometry.block_stride)
    recon = BlockReuseStream(height, width, plan, codec)
    return (*collect(run_stream(recon, frame_chunks(spikes)), height, width), codec.device)


def whole_windows(model: Spk2ImgNet, spikes: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """``model`` in PyTorch on the whole window of each centre, one window at a time (a batch
    of them at 250x400 would take gigabytes): ``(N, H, W)``."""
    frames = model.config.window_frames
    model.eval()
    images = []
    with torch.no_grad():
        for k in centers:
            window = torch.from_numpy(net_input(spikes, k, frames)[None].astype(np.float32))
            images.append(model(window)[0][0, 0].numpy())
    return np.stack(images)
