"""Running a checkpoint in PyTorch behind the same interface as the ONNX backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .checkpoint import load_model

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parents[1] / "assets" / "models" / "spk2img-default.pt"
)


class TorchPredictor:
    """``(B, 41, H, W)`` float32 0/1 windows -> ``(B, H, W)`` float32 linear intensity in [0, 1]."""

    def __init__(self, checkpoint: str | Path | None = None, threads: int | None = None):
        self.model = load_model(checkpoint or DEFAULT_CHECKPOINT)
        if threads:
            torch.set_num_threads(threads)

    @torch.inference_mode()
    def __call__(self, windows: np.ndarray) -> np.ndarray:
        image, _ = self.model(torch.from_numpy(np.ascontiguousarray(windows, np.float32)))
        return image[:, 0].numpy()
