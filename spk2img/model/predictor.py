"""Running a checkpoint in PyTorch behind the same interface as the ONNX backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from spk2img.core.block_model import code_names, head_inputs

from .block_split import AlignFuseHead, BlockEncoder
from .checkpoint import load_model

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parents[1] / "assets" / "models" / "spk2img-default.pt"
)


class TorchPredictor:
    """A checkpoint in PyTorch: ``(B, 41, H, W)`` float32 0/1 windows -> ``(B, H, W)`` float32
    linear intensity in [0, 1]; also a :class:`~spk2img.core.block_model.BlockCodec` (the block
    encoder and the align-and-fuse head, batch 1) for streams that reuse blocks."""

    def __init__(self, checkpoint: str | Path | None = None, threads: int | None = None):
        self.model = load_model(checkpoint or DEFAULT_CHECKPOINT)
        self.encoder, self.head_module = BlockEncoder(self.model), AlignFuseHead(self.model)
        cfg = self.model.config
        self.block_frames, self.block_stride = cfg.block_frames, cfg.block_stride
        self.num_blocks = cfg.num_blocks
        if threads:
            torch.set_num_threads(threads)

    @torch.inference_mode()
    def __call__(self, windows: np.ndarray) -> np.ndarray:
        image, _ = self.model(torch.from_numpy(np.ascontiguousarray(windows, np.float32)))
        return image[:, 0].numpy()

    @torch.inference_mode()
    def encode(self, block: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(13, H, W)`` spikes -> the block's code (:mod:`spk2img.core.block_model`)."""
        spikes = torch.from_numpy(np.ascontiguousarray(block, np.float32))[None]
        return tuple(t[0].numpy() for t in self.encoder(spikes))

    @torch.inference_mode()
    def head(self, codes, height: int, width: int) -> np.ndarray:
        """Five block codes in temporal order -> ``(height, width)`` linear intensity."""
        names = code_names(self.model.config.pyramid_levels)
        inputs = head_inputs(codes, names, self.num_blocks)
        image = self.head_module(*(torch.from_numpy(inputs[name]) for name in names))
        return image[0, 0, :height, :width].numpy()
