"""Running a checkpoint in PyTorch behind the same interface as the ONNX backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from spk2img.model.block_split import AlignFuseHead, BlockEncoder, model_code_names
from spk2img.model.checkpoint import load_model
from spk2img.runtime.block_codec import head_inputs

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parents[1] / "assets" / "models" / "spk2img-default.pt"
)


class TorchPredictor:
    """A checkpoint in PyTorch: ``(B, F, H, W)`` float32 0/1 windows of its ``F`` frames ->
    ``(B, H, W)`` float32 linear intensity in [0, 1]; also a
    :class:`~spk2img.runtime.block_codec.BlockCodec` (the block encoder and the align-and-fuse head,
    batch 1) for streams that reuse blocks."""

    def __init__(self, checkpoint: str | Path | None = None, threads: int | None = None):
        self.model = load_model(checkpoint or DEFAULT_CHECKPOINT)
        self.encoder, self.head_module = BlockEncoder(self.model), AlignFuseHead(self.model)
        self.geometry = self.model.config.geometry
        if threads:
            torch.set_num_threads(threads)

    @torch.inference_mode()
    def __call__(self, windows: np.ndarray) -> np.ndarray:
        image, _ = self.model(torch.from_numpy(np.ascontiguousarray(windows, np.float32)))
        return image[:, 0].numpy()

    @torch.inference_mode()
    def encode(self, block: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(block_frames, H, W)`` spikes -> the block's code
        (:mod:`spk2img.runtime.block_codec`)."""
        spikes = torch.from_numpy(np.ascontiguousarray(block, np.float32))[None]
        return tuple(t[0].numpy() for t in self.encoder(spikes))

    @torch.inference_mode()
    def head(self, codes, height: int, width: int) -> np.ndarray:
        """A window's block codes in temporal order -> ``(height, width)`` linear intensity."""
        names = model_code_names(self.model)
        inputs = head_inputs(codes, names, self.geometry.num_blocks)
        image = self.head_module(*(torch.from_numpy(inputs[name]) for name in names))
        return image[0, 0, :height, :width].numpy()
