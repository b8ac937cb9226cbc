"""Spatially adaptive light inference (SALI) of Spk2ImgNet (Zhao et al., CVPR 2021)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def fold(x: torch.Tensor, stride: int) -> torch.Tensor:
    """``(b, c, h, w)`` -> ``(b, c * stride**2, h / stride, w / stride)`` (pixel unshuffle:
    channel ``i * stride**2 + (y % stride) * stride + x % stride``); ``x`` itself for stride 1."""
    return refold(x, 1, stride)


def refold(x: torch.Tensor, stride: int, to_stride: int) -> torch.Tensor:
    """``x`` folded by ``stride`` -> the same image folded by ``to_stride`` (a multiple of it):
    ``fold(unfold(x, stride), to_stride)``, ``(b, c * s**2, h, w)`` -> ``(b, c * t**2, h * s / t,
    w * s / t)``.

    Exported to ONNX as one conv of stride ``t / s``, grouped per channel ``c``, whose one-hot
    kernels each pick one value (exact): ``pixel_unshuffle`` exports to a reshape and a 6-D
    transpose (and the pair to a DepthToSpace besides), which cost onnxruntime about 5 % of the
    ``cpu`` member's frame; ONNX's SpaceToDepth orders the channels otherwise."""
    if to_stride == stride:
        return x
    if not torch.onnx.is_in_onnx_export():
        return F.pixel_unshuffle(unfold(x, stride), to_stride)
    step, channels = to_stride // stride, x.shape[1] // stride**2
    picks = torch.zeros(to_stride**2, stride**2, step, step, dtype=x.dtype, device=x.device)
    for y in range(to_stride):
        for x_ in range(to_stride):
            source = (y % stride) * stride + x_ % stride
            picks[y * to_stride + x_, source, y // stride, x_ // stride] = 1.0
    return F.conv2d(x, picks.repeat(channels, 1, 1, 1), stride=step, groups=channels)


def unfold(x: torch.Tensor, stride: int) -> torch.Tensor:
    """The inverse of :func:`fold`: ``(b, c * stride**2, h, w)`` -> ``(b, c, h * stride, w *
    stride)``."""
    return F.pixel_shuffle(x, stride) if stride > 1 else x


class LightInference(nn.Module):
    """SALI: several intensity estimates of one spike block and an attention that weighs them.

    Each centred sub-window of the block (13, 11, 9 and 7 of 13 frames as published) goes through
    conv3x3 -> ``hidden`` -> ReLU -> conv3x3 -> 1, an estimate of ``0.6 * I`` that is short-window
    (sharp under motion) or long-window (quiet under low light). An attention
    (conv3x3 ``n -> attention_hidden``, ReLU, conv3x3 ``-> n``, sigmoid) scales the ``n``
    estimates per pixel.

    With ``stride`` ``s > 1`` it reads the block folded (:func:`fold`): every conv runs at
    ``1/s`` of the size, a branch reads its sub-window's ``n * s * s`` channels and writes the
    ``s * s`` pixels of its estimate, and the attention weighs all of them.

    Args:
        block_frames: frames of the input block.
        subwindows: lengths of the centred sub-windows, each ``<= block_frames``, same parity.
        hidden: hidden channels of each sub-window branch.
        attention_hidden: hidden channels of the attention.
        stride: resolution step, the fold of the input (1 as published).
    """

    def __init__(
        self,
        block_frames: int,
        subwindows: tuple[int, ...],
        hidden: int,
        attention_hidden: int,
        stride: int = 1,
    ) -> None:
        super().__init__()
        self.stride = stride
        pixels = stride**2  # channels per frame once folded
        self.spans = [
            ((block_frames - n) // 2 * pixels, (block_frames + n) // 2 * pixels) for n in subwindows
        ]
        self.branches = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(n * pixels, hidden, 3, padding=1),
                nn.ReLU(),
                nn.Conv2d(hidden, pixels, 3, padding=1),
            )
            for n in subwindows
        )
        estimates = len(subwindows) * pixels
        self.attention = nn.Sequential(
            nn.Conv2d(estimates, attention_hidden, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(attention_hidden, estimates, 3, padding=1),
            nn.Sigmoid(),
        )

    def forward(self, block: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``block`` ``(b, block_frames * s * s, h / s, w / s)`` spikes (``(b, block_frames, h,
        w)`` folded) -> ``(weighted, estimates)``, both ``(b, n * s * s, h / s, w / s)``
        (``(b, n, h, w)`` folded): the attention-scaled estimates (the feature extractor's
        input) and the raw estimates of ``0.6 * I`` (what the intermediate loss sees)."""
        estimates = torch.cat(
            [
                branch(block[:, start:stop])
                for branch, (start, stop) in zip(self.branches, self.spans, strict=True)
            ],
            dim=1,
        )  # (b, n * s * s, h / s, w / s)
        return self.attention(estimates) * estimates, estimates
