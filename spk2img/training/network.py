"""Spk2ImgNet (Zhao et al., "Spk2ImgNet: Learning to Reconstruct Dynamic Scene from Continuous
Spike Stream", CVPR 2021) as SPEC §4 describes it, for any :class:`Spk2ImgNetConfig`."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..core.light import SPIKE_RATE
from .alignment import FeaturePyramid, PCDAlignment
from .config import Spk2ImgNetConfig, get_config
from .features import FeatureExtractor
from .fusion import ReliabilityFusion
from .sali import LightInference


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad the bottom and right of ``(b, c, h, w)`` up to multiples of ``multiple``.

    The pad amounts are expressions of ``x.shape``, so they stay symbolic under ONNX export.
    """
    h, w = x.shape[-2:]
    return F.pad(x, (0, (-w) % multiple, 0, (-h) % multiple), mode="replicate")


class Spk2ImgNet(nn.Module):
    """Spike window -> intensity image, plus SALI's intermediate estimates.

    Args:
        config: the member's shape; :data:`~spk2img.training.config.PAPER` is the published net.
    """

    def __init__(self, config: Spk2ImgNetConfig) -> None:
        super().__init__()
        self.config = config
        c = config.channels
        self.sali = LightInference(
            config.block_frames,
            config.sali_subwindows,
            config.sali_hidden,
            config.sali_attention_hidden,
        )
        self.features = FeatureExtractor(
            len(config.sali_subwindows), c, config.residual_blocks, config.convs_per_block
        )
        self.pyramid = FeaturePyramid(c, config.pyramid_levels)
        self.align = PCDAlignment(c, config.pyramid_levels, config.deformable_groups)
        self.fusion = ReliabilityFusion(
            c, config.num_blocks, config.reliability_hidden, config.fusion_hidden
        )

    def forward(self, spikes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reconstruct the frame at the centre of a spike window.

        Args:
            spikes: ``(b, window_frames, h, w)`` float, 0/1 (41 frames ``k-20 .. k+20``).

        Returns:
            ``image`` ``(b, 1, h, w)``: linear intensity, the prediction of ``0.6 * I`` divided by
            0.6; clipped to [0, 1] in eval mode, left unclipped in training mode so that the
            L1 loss keeps its gradient where the prediction overshoots.
            ``estimates`` ``(b, num_blocks, n_subwindows, h, w)``: SALI's raw estimates of each
            block (before the attention), divided by 0.6 like ``image`` and never clipped; the
            intermediate loss compares them with the intensity at the block centres.
        """
        cfg = self.config
        h, w = spikes.shape[-2:]
        key = cfg.num_blocks // 2
        neighbours = cfg.num_blocks - 1
        spikes = pad_to_multiple(spikes, cfg.size_multiple)  # (b, t, hp, wp)

        # five 13-frame blocks at offsets 0, 7, 14, 21, 28, folded into the batch
        blocks = torch.stack(
            [
                spikes[:, start : start + cfg.block_frames]
                for start in range(0, cfg.num_blocks * cfg.block_stride, cfg.block_stride)
            ],
            dim=1,
        ).flatten(0, 1)  # (b * blocks, block_frames, hp, wp)

        # SALI and feature extraction, shared by the blocks
        weighted, estimates = self.sali(blocks)  # (b * blocks, n, hp, wp) each
        feats = self.features(weighted)  # (b * blocks, c, hp, wp)

        # align the neighbours to the key, all neighbours in one batch
        pyramid = [level.unflatten(0, (-1, cfg.num_blocks)) for level in self.pyramid(feats)]
        neighbour_pyramid = [
            torch.cat([level[:, :key], level[:, key + 1 :]], dim=1).flatten(0, 1)
            for level in pyramid
        ]  # (b * neighbours, c, h_l, w_l) per level
        key_pyramid = [
            level[:, key : key + 1].expand(-1, neighbours, -1, -1, -1).flatten(0, 1)
            for level in pyramid
        ]  # the key repeated for each neighbour
        aligned = self.align(neighbour_pyramid, key_pyramid)  # (b * neighbours, c, hp, wp)
        aligned = aligned.unflatten(0, (-1, neighbours))  # (b, neighbours, c, hp, wp)

        # reliability fusion -> 0.6 * I
        pred = self.fusion(list(aligned.unbind(1)), pyramid[0][:, key])  # (b, 1, hp, wp)

        image = pred[..., :h, :w] / SPIKE_RATE
        if not self.training:
            image = image.clamp(0, 1)
        estimates = estimates.unflatten(0, (-1, cfg.num_blocks))[..., :h, :w] / SPIKE_RATE
        return image, estimates


def build_model(member: str | Spk2ImgNetConfig) -> Spk2ImgNet:
    """A freshly initialised network for a member name (``paper``, ``small``, ...) or a config."""
    config = get_config(member) if isinstance(member, str) else member
    return Spk2ImgNet(config)
