"""Running a checkpoint in PyTorch behind the same interface as the ONNX backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from spk2img.core.block_model import code_names, head_inputs

from .checkpoint import load_model
from .network import pad_to_multiple, to_intensity

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parents[1] / "assets" / "models" / "spk2img-default.pt"
)


class TorchPredictor:
    """A checkpoint in PyTorch: ``(B, 41, H, W)`` float32 0/1 windows -> ``(B, H, W)`` float32
    linear intensity in [0, 1]; also a :class:`~spk2img.core.block_model.BlockCodec` (the block
    encoder and the align-and-fuse head, batch 1) for streams that reuse blocks."""

    def __init__(self, checkpoint: str | Path | None = None, threads: int | None = None):
        self.model = load_model(checkpoint or DEFAULT_CHECKPOINT)
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
        pyramid, nbr, key = self.model.encode(
            pad_to_multiple(spikes, self.model.config.size_multiple)
        )
        return tuple(t[0].numpy() for t in (*pyramid, *nbr, *key))

    @torch.inference_mode()
    def head(self, codes, height: int, width: int) -> np.ndarray:
        """Five block codes in temporal order -> ``(height, width)`` linear intensity."""
        levels = self.model.config.pyramid_levels
        inputs = head_inputs(codes, code_names(levels), self.num_blocks)
        tensors = [torch.from_numpy(a) for a in inputs.values()]
        pred = self.model.head(*(tensors[i * levels : (i + 1) * levels] for i in range(3)))
        return to_intensity(pred, height, width, training=False)[0, 0].numpy()
