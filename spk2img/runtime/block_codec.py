"""The network in two parts for streams: encode each 13-frame block once, then align and fuse.

A :class:`BlockCodec` turns one block into its *code* (feature pyramid and offset-conv terms,
:mod:`spk2img.model.block_split` has the layout) and five codes into an image.
:class:`OnnxBlockCodec` runs the exported encoder and head graphs with onnxruntime (no torch);
``spk2img.runtime.torch_backend.TorchPredictor`` runs the same split in PyTorch.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from spk2img.errors import InputError
from spk2img.model.block_code import code_names, code_role, reads_sali, role_blocks
from spk2img.model.config import Geometry
from spk2img.runtime.onnx_backend import create_session, model_path, run_session

PART_FILES = {"encoder": ".encoder.onnx", "head": ".head.onnx"}
"""Suffixes that replace ``.onnx`` of the one-shot graph for its two parts."""

BlockCode = tuple[np.ndarray, ...]
"""One block's code: :func:`code_names` order, ``(c, h_l, w_l)`` float32 each."""


class BlockCodec(Protocol):
    """Block encoder and align-and-fuse head of one network (batch 1)."""

    geometry: Geometry
    """The network's window and blocks (13-frame blocks 7 apart, five a window, as published)."""

    def encode(self, block: np.ndarray) -> BlockCode:
        """``(block_frames, H, W)`` 0/1 spikes -> the block's code."""
        ...

    def head(self, codes: Sequence[BlockCode], height: int, width: int) -> np.ndarray:
        """The codes of a window's blocks in temporal order -> ``(height, width)`` float32
        linear intensity in [0, 1]."""
        ...


def block_graph_paths(model: str | Path) -> dict[str, Path]:
    """``{part: path}`` of the encoder and head exported beside the one-shot graph ``model``."""
    model = Path(model)
    return {part: model.with_suffix(suffix) for part, suffix in PART_FILES.items()}


class OnnxBlockCodec:
    """The encoder and head graphs beside a one-shot graph, run with onnxruntime.

    Args:
        model: the one-shot graph (default: the shipped model); its parts are found by
            :func:`block_graph_paths`.
        threads: onnxruntime intra-op threads of each session (None: onnxruntime's default).
        device: where both graphs run (:data:`~spk2img.runtime.onnx_backend.DEVICES`).
        io_binding: run through onnxruntime's IO binding (default: on a GPU).
        memory_arena: keep onnxruntime's CPU memory arena in both sessions
            (:func:`~spk2img.runtime.onnx_backend.session_options`).

    Raises :class:`InputError` when a part is missing or the parts hold other weights than
    each other (their ``weights_sha256`` metadata differ).
    """

    def __init__(
        self,
        model: str | Path | None = None,
        threads: int | None = None,
        device: str = "cpu",
        io_binding: bool | None = None,
        memory_arena: bool = False,
    ):
        paths = block_graph_paths(model_path(model))
        arena = {"memory_arena": memory_arena}
        self.parts = {"encoder": create_session(paths["encoder"], threads, device, **arena)}
        self.device = self.parts["encoder"].device
        """The concrete device both graphs run on."""
        self.parts["head"] = create_session(paths["head"], threads, self.device, **arena)
        self.encoder = self.parts["encoder"].session
        self.head_session = self.parts["head"].session
        self.image_name = self.head_session.get_outputs()[0].name
        self.io_binding = self.device != "cpu" if io_binding is None else io_binding
        sessions = (self.encoder, self.head_session)
        meta = [dict(session.get_modelmeta().custom_metadata_map) for session in sessions]
        if meta[0].get("weights_sha256") != meta[1].get("weights_sha256"):
            raise InputError(
                f"{paths['encoder']} and {paths['head']} hold different weights "
                "(weights_sha256 differs): export them again together"
            )
        self.metadata = meta[0]
        self.geometry = Geometry.from_metadata(self.metadata)
        config = json.loads(self.metadata["config"])
        sali = reads_sali(int(config.get("detail_hidden", 0)), bool(config.get("flow_guided")))
        self.names = code_names(int(config["pyramid_levels"]), sali)

    def encode(self, block: np.ndarray) -> BlockCode:
        feeds = {"block": np.ascontiguousarray(block[None], np.float32)}
        outputs = run_session(self.parts["encoder"], feeds, self.names, self.io_binding)
        return tuple(out[0] for out in outputs)

    def head(self, codes: Sequence[BlockCode], height: int, width: int) -> np.ndarray:
        feeds = head_inputs(codes, self.names, self.geometry.num_blocks)
        (image,) = run_session(self.parts["head"], feeds, [self.image_name], self.io_binding)
        return image[0, 0, :height, :width]


def head_inputs(codes: Sequence[BlockCode], names: list[str], num_blocks: int) -> dict:
    """The head's inputs from a window's block codes: every block's ``feat_l*`` (and ``sali``,
    where the code has one) stacked ``(1, blocks, c, h, w)``, the neighbours' ``nbr_l*``
    ``(1, blocks - 1, ...)``, the key's ``key_l*`` ``(1, c, h, w)``."""
    if len(codes) != num_blocks:
        raise ValueError(f"the head takes {num_blocks} block codes, got {len(codes)}")
    key = num_blocks // 2
    neighbours = [code for i, code in enumerate(codes) if i != key]
    stacks = role_blocks(num_blocks)
    feeds = {}
    for index, name in enumerate(names):
        stacked = stacks[code_role(name)]
        if stacked is None:
            feeds[name] = codes[key][index][None]
        else:
            picked = codes if stacked == num_blocks else neighbours
            feeds[name] = np.stack([code[index] for code in picked])[None]
    return feeds
