"""The network split for streams: a block encoder and an align-and-fuse head.

The windows of centres ``k`` and ``k + 7`` share four of their five 13-frame blocks. The encoder
turns one block into its *code* and the head turns a window's five codes into the image, so a
stream encodes each block once. Both wrap a plain :class:`~spk2img.model.network.Spk2ImgNet`
(same modules, same weights); encoder then head equals its forward to float rounding.

A block's code, per pyramid level ``l = 1 .. L`` (level 1 at ``1/s`` of the padded size, ``s``
the feature stride, each further level half the one before):

- ``feat_l{l}`` ``(b, c, h_l, w_l)``: the block's feature pyramid;
- ``nbr_l{l}``, ``key_l{l}`` ``(b, c, h_l, w_l)``: its terms of level ``l``'s first offset conv
  as a neighbour and as the key. That conv is linear in ``[neighbour, key]``, so its output on a
  pair is the neighbour's term plus the key's, and each block's terms are computed once, for
  whichever pairs it takes part in;
- ``sali`` ``(b, n * r * r, hp / r, wp / r)``, only in members with a detail refinement or a
  motion-guided alignment (the blocks' motion is found from them): its weighted SALI estimates
  (``r`` the SALI stride).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .alignment import PCDAlignment
from .block_code import code_names, code_role, reads_sali, role_blocks
from .block_ops import per_neighbour, without_key
from .network import Spk2ImgNet, pad_to_multiple, to_intensity
from .sali import fold


def neighbour_terms(align: PCDAlignment, pyramid: list[torch.Tensor]) -> list[torch.Tensor]:
    """A block's share of each level's first offset conv as the neighbour: pyramid (level 1
    first) of ``(b, c, h_l, w_l)`` -> the same shapes (no bias)."""
    c = pyramid[0].shape[1]
    return [
        F.conv2d(feat, align.offset_conv1[f"l{i}"].weight[:, :c], None, padding=1)
        for i, feat in enumerate(pyramid, start=1)
    ]


def key_terms(align: PCDAlignment, pyramid: list[torch.Tensor]) -> list[torch.Tensor]:
    """A block's share of each level's first offset conv as the key (with the bias): pyramid
    of ``(b, c, h_l, w_l)`` -> the same shapes."""
    c = pyramid[0].shape[1]
    convs = [align.offset_conv1[f"l{i}"] for i in range(1, len(pyramid) + 1)]
    return [
        F.conv2d(feat, conv.weight[:, c:], conv.bias, padding=1)
        for conv, feat in zip(convs, pyramid, strict=True)
    ]


def model_code_names(model: Spk2ImgNet) -> list[str]:
    """The names of ``model``'s block code, in the order the encoder returns it."""
    cfg = model.config
    return code_names(cfg.pyramid_levels, reads_sali(cfg.detail_hidden, cfg.flow_guided))


def repeated_code(
    codes: tuple[torch.Tensor, ...], names: list[str], num_blocks: int
) -> tuple[torch.Tensor, ...]:
    """One block's code (named ``names``) as a whole window's head inputs (every block the
    same): the example inputs of tracing and of counting the head's cost."""
    stacks = [role_blocks(num_blocks)[code_role(name)] for name in names]
    return tuple(
        code if n is None else code.unsqueeze(1).expand(-1, n, *code.shape[1:])
        for code, n in zip(codes, stacks, strict=True)
    )


class BlockEncoder(nn.Module):
    """``(b, 13, H, W)`` spikes -> the flat tuple of one block's code (in the order of
    :func:`~spk2img.model.block_code.code_names`); ``H`` and ``W`` are padded to the network's
    size multiple inside."""

    def __init__(self, model: Spk2ImgNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, block: torch.Tensor) -> tuple[torch.Tensor, ...]:
        net = self.model
        cfg = net.config
        weighted, _ = net.sali(fold(pad_to_multiple(block, cfg.size_multiple), cfg.sali_stride))
        pyramid = net.block_pyramid(weighted)
        sali = (weighted,) if reads_sali(cfg.detail_hidden, cfg.flow_guided) else ()
        return (
            *pyramid,
            *neighbour_terms(net.align, pyramid),
            *key_terms(net.align, pyramid),
            *sali,
        )


class AlignFuseHead(nn.Module):
    """A window's block codes -> ``(b, 1, hp, wp)`` linear intensity in [0, 1], still padded.

    Inputs in the order of :func:`~spk2img.model.block_code.code_names`: ``feat_l*``
    ``(b, blocks, c, h_l, w_l)`` (every block in temporal order), ``nbr_l*``
    ``(b, blocks - 1, c, h_l, w_l)`` (the neighbours in order), ``key_l*``
    ``(b, c, h_l, w_l)`` (the key block's) and, with a detail refinement or a motion-guided
    alignment, every block's ``sali`` ``(b, blocks, n * r * r, hp / r, wp / r)``.
    """

    def __init__(self, model: Spk2ImgNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, *codes: torch.Tensor) -> torch.Tensor:
        net, cfg = self.model, self.model.config
        levels, key, neighbours = cfg.pyramid_levels, cfg.num_blocks // 2, cfg.num_blocks - 1
        pyramid, nbr_terms, key_terms_ = (
            list(codes[i * levels : (i + 1) * levels]) for i in range(3)
        )
        weighted = codes[3 * levels] if reads_sali(cfg.detail_hidden, cfg.flow_guided) else None
        motion = None if weighted is None else net.block_motion(weighted)
        key_feat = pyramid[0][:, key]  # (b, c, h_f, w_f)
        aligned = net.align.align_levels(
            [without_key(level, key).flatten(0, 1) for level in pyramid],
            [
                n.flatten(0, 1) + per_neighbour(k, neighbours)
                for n, k in zip(nbr_terms, key_terms_, strict=True)
            ],
            per_neighbour(key_feat, neighbours),
            motion if cfg.flow_guided else None,
        ).unflatten(0, (-1, neighbours))  # (b, neighbours, c, h_f, w_f)
        pred = net.fuse(list(aligned.unbind(1)), key_feat, weighted, motion)
        return to_intensity(pred, pred.shape[-2], pred.shape[-1], training=False)
