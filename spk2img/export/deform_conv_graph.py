"""Exporting the modulated deformable convs as ONNX ``DeformConv`` (opset 19) nodes.

No torchvision: while :func:`deform_conv_as_custom_op` is active, the network's deformable convs
call ``torch.ops.spk2img.modulated_deform_conv2d``, a custom op whose eager kernel is the
grid_sample implementation of :mod:`spk2img.model.deform_conv` (so the traced model computes
the same thing) and which :data:`DEFORM_CONV_TRANSLATION` turns into one ``DeformConv`` node.

Semantics agree (docs/export.md; ONNX ``DeformConv`` reference implementation): the offset input is
``(b, offset_group * 2 * kh * kw, h_out, w_out)`` read as ``(offset_group, kh, kw, [dy, dx])``,
the mask ``(b, offset_group * kh * kw, h_out, w_out)`` as ``(offset_group, kh, kw)``, taps
sample at ``(y - pad + i * dil + dy, x - pad + j * dil + dx)`` bilinearly with zeros outside
the input, ``X`` channels are split into ``offset_group`` consecutive blocks.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from unittest import mock

import torch
from onnxscript import opset19

from spk2img.model import deform_conv
from spk2img.model.deform_conv import modulated_deform_conv2d as grid_sample_deform_conv2d

DEFORM_CONV_OPSET = 19


@torch.library.custom_op("spk2img::modulated_deform_conv2d", mutates_args=())
def modulated_deform_conv2d_op(
    x: torch.Tensor,
    offset: torch.Tensor,
    mask: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor,
    groups: int,
    padding: int = 1,
    dilation: int = 1,
) -> torch.Tensor:
    """:func:`spk2img.model.deform_conv.modulated_deform_conv2d` as one opaque op (stride 1):
    ``x`` ``(b, c_in, h, w)``, ``offset`` ``(b, groups * 2 * K, h_out, w_out)`` in pixels,
    ``mask`` ``(b, groups * K, h_out, w_out)`` in [0, 1], ``weight`` ``(c_out, c_in, kh, kw)``,
    ``bias`` ``(c_out,)`` -> ``(b, c_out, h_out, w_out)``."""
    return grid_sample_deform_conv2d(x, offset, mask, weight, bias, groups, padding, dilation)


@modulated_deform_conv2d_op.register_fake
def _(x, offset, mask, weight, bias, groups, padding=1, dilation=1):
    return x.new_empty(x.shape[0], weight.shape[0], offset.shape[2], offset.shape[3])


def deform_conv_onnx(
    x, offset, mask, weight, bias, groups: int, padding: int = 1, dilation: int = 1
):
    """The custom op as one ONNX ``DeformConv`` (inputs ``X, W, offset, B, mask``)."""
    return opset19.DeformConv(
        x,
        weight,
        offset,
        bias,
        mask,
        dilations=[dilation, dilation],
        offset_group=groups,
        pads=[padding, padding, padding, padding],
        strides=[1, 1],
    )


DEFORM_CONV_TRANSLATION = {torch.ops.spk2img.modulated_deform_conv2d.default: deform_conv_onnx}
"""``custom_translation_table`` for ``torch.onnx.export``: the custom op -> ``DeformConv``."""


@contextmanager
def deform_conv_as_custom_op() -> Iterator[None]:
    """Route :class:`~spk2img.model.deform_conv.ModulatedDeformConv2d` through the custom op
    (by swapping the function its ``forward`` calls) for as long as the context lasts."""
    with mock.patch.object(deform_conv, "modulated_deform_conv2d", modulated_deform_conv2d_op):
        yield
