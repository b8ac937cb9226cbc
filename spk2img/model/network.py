"""Spk2ImgNet (Zhao et al., "Spk2ImgNet: Learning to Reconstruct Dynamic Scene from Continuous
Spike Stream", CVPR 2021) as SPEC §4 describes it, for any :class:`Spk2ImgNetConfig`."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from spk2img.core.light import SPIKE_RATE

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
        config: the member's shape; :data:`~spk2img.model.config.PAPER` is the published net.
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
        spikes = pad_to_multiple(spikes, cfg.size_multiple)  # (b, t, hp, wp)

        # five 13-frame blocks at offsets 0, 7, 14, 21, 28, folded into the batch
        blocks = torch.stack(
            [
                spikes[:, start : start + cfg.block_frames]
                for start in range(0, cfg.num_blocks * cfg.block_stride, cfg.block_stride)
            ],
            dim=1,
        ).flatten(0, 1)  # (b * blocks, block_frames, hp, wp)

        # SALI, features and pyramid, shared by the blocks
        weighted, estimates = self.sali(blocks)  # (b * blocks, n, hp, wp) each
        pyramid = [
            level.unflatten(0, (-1, cfg.num_blocks))
            for level in self.pyramid(self.features(weighted))
        ]  # (b, blocks, c, h_l, w_l) per level

        # the first offset conv's terms: as neighbour for the neighbours, as key for the key
        neighbours = [_without_key(level, key).flatten(0, 1) for level in pyramid]
        neighbour_terms = [
            terms.unflatten(0, (-1, cfg.num_blocks - 1))
            for terms in self.align.neighbour_terms(neighbours)
        ]  # (b, neighbours, c, h_l, w_l) per level
        key_terms = self.align.key_terms([level[:, key] for level in pyramid])

        image = to_intensity(self.head(pyramid, neighbour_terms, key_terms), h, w, self.training)
        estimates = estimates.unflatten(0, (-1, cfg.num_blocks))[..., :h, :w] / SPIKE_RATE
        return image, estimates

    def encode(
        self, block: torch.Tensor
    ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """Everything the head needs of one temporal block, for any role it will play.

        Args:
            block: ``(b, block_frames, hp, wp)`` spikes, ``hp`` and ``wp`` multiples of
                ``config.size_multiple``.

        Returns:
            ``(pyramid, neighbour_terms, key_terms)``: lists over levels (level 1 first) of
            ``(b, c, hp / 2**(l-1), wp / 2**(l-1))``: the feature pyramid and the block's terms
            of the first offset conv as a neighbour and as the key.
        """
        weighted, _ = self.sali(block)
        pyramid = self.pyramid(self.features(weighted))
        return pyramid, self.align.neighbour_terms(pyramid), self.align.key_terms(pyramid)

    def head(
        self,
        pyramid: list[torch.Tensor],
        neighbour_terms: list[torch.Tensor],
        key_terms: list[torch.Tensor],
    ) -> torch.Tensor:
        """Align the neighbours to the key and fuse: the prediction of ``0.6 * I``.

        Args:
            pyramid: per level, ``(b, blocks, c, h_l, w_l)``: every block's features in
                temporal order.
            neighbour_terms: per level, ``(b, blocks - 1, c, h_l, w_l)``: the neighbours' terms
                (:meth:`~spk2img.model.alignment.PCDAlignment.neighbour_terms`), in order.
            key_terms: per level, ``(b, c, h_l, w_l)``: the key's terms.

        Returns:
            ``(b, 1, hp, wp)``, padded like the input, not scaled or clipped.
        """
        cfg = self.config
        key = cfg.num_blocks // 2
        neighbours = cfg.num_blocks - 1
        key_feat = pyramid[0][:, key]  # (b, c, hp, wp)

        def per_neighbour(tensor: torch.Tensor) -> torch.Tensor:  # the key's, once a neighbour
            return tensor.unsqueeze(1).expand(-1, neighbours, -1, -1, -1).flatten(0, 1)

        # align the neighbours to the key, all neighbours in one batch
        aligned = self.align(
            [_without_key(level, key).flatten(0, 1) for level in pyramid],
            [terms.flatten(0, 1) for terms in neighbour_terms],
            [per_neighbour(terms) for terms in key_terms],
            per_neighbour(key_feat),
        ).unflatten(0, (-1, neighbours))  # (b, neighbours, c, hp, wp)

        # reliability fusion -> 0.6 * I
        return self.fusion(list(aligned.unbind(1)), key_feat)


def _without_key(level: torch.Tensor, key: int) -> torch.Tensor:
    """``(b, blocks, ...)`` -> ``(b, blocks - 1, ...)``: the neighbours, in temporal order."""
    return torch.cat([level[:, :key], level[:, key + 1 :]], dim=1)


def to_intensity(pred: torch.Tensor, height: int, width: int, training: bool) -> torch.Tensor:
    """The head's padded ``0.6 * I`` ``(b, 1, hp, wp)`` -> ``I`` ``(b, 1, height, width)``,
    clipped to [0, 1] unless ``training``."""
    image = pred[..., :height, :width] / SPIKE_RATE
    return image if training else image.clamp(0, 1)


def build_model(member: str | Spk2ImgNetConfig) -> Spk2ImgNet:
    """A freshly initialised network for a member name (``paper``, ``small``, ...) or a config."""
    config = get_config(member) if isinstance(member, str) else member
    return Spk2ImgNet(config)
