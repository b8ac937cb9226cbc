"""Modulated deformable convolution (DCNv2) built on ``grid_sample``, so it exports to ONNX.

Semantics as torchvision's ``deform_conv2d`` with a mask (docs/export.md): for offset group
``g`` and kernel tap ``k = i * kw + j``, offset channel ``g * 2K + 2k`` is ``dy`` and
``g * 2K + 2k + 1`` is ``dx``, mask channel ``g * K + k`` scales the sample, and the tap samples
the input at ``(y - pad + i * dil + dy, x - pad + j * dil + dx)``, bilinearly, zero outside the
image. Stride is 1.

All ``K`` taps of all groups are sampled by one ``grid_sample`` call on a
``(b * groups, K * h_out, w_out, 2)`` grid; one 1x1 convolution then applies the weights.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterator, Mapping
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import nn

from .warp import sampling_grid


def modulated_deform_conv2d(
    x: torch.Tensor,
    offset: torch.Tensor,
    mask: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    groups: int,
    padding: int = 1,
    dilation: int = 1,
) -> torch.Tensor:
    """Modulated deformable convolution, stride 1.

    Args:
        x: input ``(b, c_in, h, w)``.
        offset: ``(b, groups * 2 * K, h_out, w_out)``, ``(dy, dx)`` pairs per tap, in pixels.
        mask: ``(b, groups * K, h_out, w_out)``, the modulation of each tap (already sigmoided).
        weight: ``(c_out, c_in, kh, kw)`` with ``K = kh * kw``.
        bias: ``(c_out,)`` or ``None``.
        groups: offset (deformable) groups; ``c_in`` channels are split into ``groups`` blocks.
        padding: implicit zero padding of the input on every side.
        dilation: spacing of the kernel taps.

    Returns:
        ``(b, c_out, h_out, w_out)`` with ``h_out = h + 2 * padding - dilation * (kh - 1)``.
    """
    b, c_in, h, w = x.shape
    kh, kw = weight.shape[-2:]
    taps = kh * kw
    h_out, w_out = offset.shape[-2:]

    # sampling positions in input pixels, (b, groups * K, h_out, w_out) each: channel
    # g * K + k is tap k of group g, as in the mask (every tensor stays 4-D: the symbolic
    # shapes of the export stay few). In float32 at least, sampled from an input as wide: under
    # bf16 autocast a position of 37.3 px would round to 37.25 (and 300.3 to 300)
    exact = torch.promote_types(x.dtype, torch.float32)
    tap_y = torch.arange(kh, dtype=exact, device=x.device) * dilation - padding
    tap_x = torch.arange(kw, dtype=exact, device=x.device) * dilation - padding
    tap_y = tap_y.repeat_interleave(kw).repeat(groups).view(1, -1, 1, 1)  # i of k = i * kw + j
    tap_x = tap_x.repeat(kh * groups).view(1, -1, 1, 1)  # j of k = i * kw + j
    rows = torch.arange(h_out, dtype=exact, device=x.device).view(1, 1, -1, 1)
    cols = torch.arange(w_out, dtype=exact, device=x.device).view(1, 1, 1, -1)
    offset = offset.to(exact)
    sample_y = offset[:, 0::2] + (rows + tap_y)
    sample_x = offset[:, 1::2] + (cols + tap_x)

    grid = sampling_grid(sample_y, sample_x, h, w).reshape(b * groups, taps * h_out, w_out, 2)
    sampled = F.grid_sample(
        x.to(exact).reshape(b * groups, c_in // groups, h, w),
        grid,
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )  # (b * groups, c_in / groups, K * h_out, w_out)
    sampled = sampled * mask.reshape(b * groups, 1, taps * h_out, w_out)

    # channel order (c_in, K) matches weight.reshape(c_out, c_in * K)
    columns = sampled.reshape(b, c_in * taps, h_out, w_out)
    return F.conv2d(columns, weight.reshape(weight.shape[0], c_in * taps, 1, 1), bias)


class ModulatedDeformConv2d(nn.Module):
    """DCNv2 pack as in EDVR's ``DCN_sep``: a 3x3 modulated deformable conv whose offsets and
    mask are predicted from a separate conditioning feature.

    ``conv_offset_mask`` (3x3, ``condition_channels -> 3 * K * groups``) gives the offsets (first
    ``2 * K * groups`` channels) and the mask logits (last ``K * groups``); it starts at zero, so
    a fresh module is a plain convolution scaled by 0.5.

    Args:
        in_channels: channels of the sampled input.
        out_channels: channels of the output.
        condition_channels: channels of the feature that predicts offsets and mask.
        groups: deformable (offset) groups; must divide ``in_channels``.
    """

    kernel_size = 3

    def __init__(
        self, in_channels: int, out_channels: int, condition_channels: int, groups: int
    ) -> None:
        super().__init__()
        if in_channels % groups:
            raise ValueError(f"groups={groups} must divide in_channels={in_channels}")
        self.groups = groups
        taps = self.kernel_size**2
        size = (out_channels, in_channels, self.kernel_size, self.kernel_size)
        self.weight = nn.Parameter(torch.empty(size))
        self.bias = nn.Parameter(torch.empty(out_channels))
        self.conv_offset_mask = nn.Conv2d(condition_channels, 3 * taps * groups, 3, padding=1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Weight and bias like ``nn.Conv2d``'s; offsets and mask logits start at zero."""
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        bound = 1 / math.sqrt(self.weight[0].numel())
        nn.init.uniform_(self.bias, -bound, bound)
        nn.init.zeros_(self.conv_offset_mask.weight)
        nn.init.zeros_(self.conv_offset_mask.bias)

    def mean_shift(
        self, offset_mask: torch.Tensor, flow: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The mean over taps and groups of the offsets in ``conv_offset_mask``'s output
        ``(b, 3 * K * groups, h, w)``, plus the guiding ``flow`` ``(b, 2, h, w)`` if any: where
        the conv samples, on average, relative to a plain conv, ``(b, 2, h, w)`` ``(dy, dx)``
        px (:mod:`spk2img.evaluation.alignment_probe`, ``--align-weight``)."""
        taps = self.kernel_size**2
        offset = offset_mask[:, : 2 * taps * self.groups].unflatten(1, (-1, 2)).mean(dim=1)
        return offset if flow is None else offset + flow

    def forward(
        self, x: torch.Tensor, condition: torch.Tensor, flow: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``x`` ``(b, in, h, w)``, ``condition`` ``(b, condition_channels, h, w)`` and
        optionally a ``flow`` ``(b, 2, h, w)`` (``(dy, dx)`` px, added to every tap's offset:
        the predicted offsets are then what is left of the motion) -> ``(b, out, h, w)``."""
        offset_mask = self.conv_offset_mask(condition)  # (b, 3 * K * groups, h, w)
        offset, mask_logits = offset_mask.split(
            [2 * self.kernel_size**2 * self.groups, self.kernel_size**2 * self.groups], dim=1
        )
        if flow is not None:  # offsets read as (group, tap, [dy, dx])
            offset = (offset.unflatten(1, (-1, 2)) + flow.unsqueeze(1)).flatten(1, 2)
        return modulated_deform_conv2d(
            x, offset, torch.sigmoid(mask_logits), self.weight, self.bias, self.groups
        )


@contextmanager
def recorded_mean_shifts(
    convs: Mapping[Hashable, ModulatedDeformConv2d],
) -> Iterator[dict[Hashable, torch.Tensor]]:
    """While inside, each forward pass through a conv of ``convs`` records its
    :meth:`~ModulatedDeformConv2d.mean_shift` ``(b, 2, h, w)`` (with its gradient, if any) under
    its key in the yielded dict, from the offsets the conv computed itself (nothing is
    recomputed)."""
    shifts: dict[Hashable, torch.Tensor] = {}
    flows: dict[Hashable, torch.Tensor | None] = {}

    def take_flow(key: Hashable):
        def hook(_conv: ModulatedDeformConv2d, inputs: tuple) -> None:
            flows[key] = inputs[2] if len(inputs) > 2 else None

        return hook

    def take_offsets(key: Hashable, conv: ModulatedDeformConv2d):
        def hook(_module: nn.Module, _inputs: tuple, offset_mask: torch.Tensor) -> None:
            shifts[key] = conv.mean_shift(offset_mask, flows.pop(key))

        return hook

    handles = []
    for key, conv in convs.items():
        handles.append(conv.register_forward_pre_hook(take_flow(key)))
        handles.append(conv.conv_offset_mask.register_forward_hook(take_offsets(key, conv)))
    try:
        yield shifts
    finally:
        for handle in handles:
            handle.remove()
