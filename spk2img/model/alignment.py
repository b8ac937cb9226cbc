"""Pyramid, cascading and deformable (PCD) alignment, after EDVR (Wang et al., CVPRW 2019)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .deform_conv import ModulatedDeformConv2d
from .warp import upsample_flow


def _conv(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1)


def _zero_conv(in_channels: int, out_channels: int) -> nn.Conv2d:
    """A 3x3 conv whose weights and bias start at zero (it adds nothing until trained)."""
    conv = _conv(in_channels, out_channels)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    return conv


def _upsample(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)


def level_flow(flow: torch.Tensor | None, level: int) -> torch.Tensor | None:
    """Level-1 motion ``(b, 2, h, w)`` (pixels) at pyramid level ``level``: averaged over
    ``2**(level-1)`` squares and in that level's pixels (None stays None)."""
    if flow is None or level == 1:
        return flow
    scale = 2 ** (level - 1)
    return F.avg_pool2d(flow, scale) / scale


class FeaturePyramid(nn.Module):
    """Level ``l`` is level ``l - 1`` through a stride-2 conv3x3 and a conv3x3, each with
    LeakyReLU 0.1; level 1 is the input.

    Args:
        channels: feature channels at every level.
        levels: pyramid levels (3 as published: 1, 1/2, 1/4 of the size).
    """

    def __init__(self, channels: int, levels: int) -> None:
        super().__init__()
        self.downsample = nn.ModuleList(
            nn.Sequential(
                _conv(channels, channels, stride=2),
                nn.LeakyReLU(0.1),
                _conv(channels, channels),
                nn.LeakyReLU(0.1),
            )
            for _ in range(levels - 1)
        )

    def forward(self, feat: torch.Tensor) -> list[torch.Tensor]:
        """``(b, c, h, w)``, ``h`` and ``w`` multiples of ``2**(levels-1)`` -> one
        ``(b, c, h / 2**(l-1), w / 2**(l-1))`` per level ``l = 1 .. levels``."""
        pyramid = [feat]
        for downsample in self.downsample:
            pyramid.append(downsample(pyramid[-1]))
        return pyramid


class PCDAlignment(nn.Module):
    """Aligns a neighbour's feature pyramid to the key's, coarse to fine, then once more at
    full size (the cascade).

    At level ``l`` the offset feature comes from ``[neighbour, key]`` and, below the coarsest
    level, from the level ``l + 1`` offset feature upsampled and doubled (motion in pixels
    doubles from level to level); a modulated deformable conv samples the neighbour with it,
    and the result is fused with the upsampled level ``l + 1`` result. LeakyReLU 0.1 after every
    conv except the level-1 fusion (as in EDVR).

    Where ``reads_motion``, each level's first offset feature also reads the neighbour's
    motion to the key (the ``flow`` of :meth:`forward`, at the level's size and in its pixels)
    through a 3x3 conv of its own that starts at zero (as BasicVSR++'s offset convs read the
    flow), so the network starts as it was and correcting a guide that finds only part of the
    motion is linear in what the offsets are computed from.

    Args:
        channels: feature channels.
        levels: pyramid levels.
        groups: deformable groups of every deformable conv.
        reads_motion: whether the offset features read the motion (it must then be given).
    """

    def __init__(self, channels: int, levels: int, groups: int, reads_motion: bool = False) -> None:
        super().__init__()
        self.levels = levels
        self.motion_conv = (
            nn.ModuleDict({f"l{i}": _zero_conv(2, channels) for i in range(levels, 0, -1)})
            if reads_motion
            else None
        )
        self.offset_conv1 = nn.ModuleDict()
        self.offset_conv2 = nn.ModuleDict()
        self.offset_conv3 = nn.ModuleDict()
        self.dcn_pack = nn.ModuleDict()
        self.feat_conv = nn.ModuleDict()
        for i in range(levels, 0, -1):
            level = f"l{i}"
            coarsest = i == levels
            self.offset_conv1[level] = _conv(2 * channels, channels)
            self.offset_conv2[level] = _conv(channels if coarsest else 2 * channels, channels)
            if not coarsest:
                self.offset_conv3[level] = _conv(channels, channels)
                self.feat_conv[level] = _conv(2 * channels, channels)
            self.dcn_pack[level] = ModulatedDeformConv2d(channels, channels, channels, groups)
        self.cas_offset_conv1 = _conv(2 * channels, channels)
        self.cas_offset_conv2 = _conv(channels, channels)
        self.cas_dcn_pack = ModulatedDeformConv2d(channels, channels, channels, groups)
        self.lrelu = nn.LeakyReLU(0.1)

    def forward(
        self,
        neighbour: list[torch.Tensor],
        key: list[torch.Tensor],
        flow: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Align one neighbour per batch item to its key.

        Args:
            neighbour: the neighbour's pyramid, level 1 first, ``(b, c, h_l, w_l)`` per level.
            key: the key's pyramid, the same shapes.
            flow: the neighbour's motion to the key ``(b, 2, h, w)`` (``(dy, dx)``, level-1
                pixels), or None: each pyramid level's deformable conv adds it (averaged and
                scaled to the level) to its offsets, and where ``reads_motion`` its offset
                features read it too.

        Returns:
            The aligned neighbour ``(b, c, h, w)``.
        """
        first_offsets = [
            self.offset_conv1[f"l{i}"](torch.cat([nbr, k], dim=1))
            for i, (nbr, k) in enumerate(zip(neighbour, key, strict=True), start=1)
        ]
        return self.align_levels(neighbour, first_offsets, key[0], flow)

    def align_levels(
        self,
        neighbour: list[torch.Tensor],
        first_offsets: list[torch.Tensor],
        key_feat: torch.Tensor,
        flow: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The pyramid and the cascade, given each level's first offset conv on
        ``[neighbour, key]`` (before its LeakyReLU): :meth:`forward` computes it from the pair,
        :mod:`spk2img.model.block_split` from per-block terms.

        Args:
            neighbour: the neighbour's pyramid, ``(b, c, h_l, w_l)`` per level, level 1 first.
            first_offsets: ``offset_conv1`` of each level on ``[neighbour, key]``, same shapes.
            key_feat: the key's level-1 features ``(b, c, h, w)`` (for the cascade).
            flow: as in :meth:`forward`.

        Returns:
            The aligned neighbour ``(b, c, h, w)``.
        """
        if self.motion_conv is not None and flow is None:
            raise ValueError("this alignment's offsets read the motion: give its flow")
        upsampled_offset: torch.Tensor | None = None  # from level l + 1, (b, c, h_l, w_l)
        upsampled_feat: torch.Tensor | None = None
        for i in range(self.levels, 0, -1):
            level = f"l{i}"
            offset = first_offsets[i - 1]  # (b, c, h_l, w_l)
            if self.motion_conv is not None:
                offset = offset + self.motion_conv[level](level_flow(flow, i))
            offset = self.lrelu(offset)
            if upsampled_offset is None:  # coarsest level
                offset = self.lrelu(self.offset_conv2[level](offset))
            else:
                offset = torch.cat([offset, upsampled_offset], dim=1)
                offset = self.lrelu(self.offset_conv2[level](offset))
                offset = self.lrelu(self.offset_conv3[level](offset))
            feat = self.dcn_pack[level](neighbour[i - 1], offset, level_flow(flow, i))
            if upsampled_feat is not None:
                feat = self.feat_conv[level](torch.cat([feat, upsampled_feat], dim=1))
            if i > 1:
                feat = self.lrelu(feat)
                upsampled_offset = upsample_flow(offset)  # x2 as EDVR: motion doubles per level
                upsampled_feat = _upsample(feat)

        # cascade at level 1
        offset = torch.cat([feat, key_feat], dim=1)
        offset = self.lrelu(self.cas_offset_conv1(offset))
        offset = self.lrelu(self.cas_offset_conv2(offset))
        return self.lrelu(self.cas_dcn_pack(feat, offset))  # (b, c, h, w)
