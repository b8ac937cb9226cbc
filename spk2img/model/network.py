"""Spk2ImgNet (Zhao et al., "Spk2ImgNet: Learning to Reconstruct Dynamic Scene from Continuous
Spike Stream", CVPR 2021) as docs/architecture.md describes it, for any
:class:`Spk2ImgNetConfig`."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from spk2img.io.light import SPIKE_RATE

from .alignment import FeaturePyramid, PCDAlignment
from .block_ops import per_neighbour, without_key
from .config import Spk2ImgNetConfig, get_config
from .detail import DetailRefinement
from .features import FeatureExtractor
from .fusion import ReliabilityFusion
from .motion import block_motion
from .sali import LightInference, fold, refold, unfold
from .warp import upsample_flow


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad the bottom and right of ``(b, c, h, w)`` up to multiples of ``multiple``.

    The pad amounts are expressions of ``x.shape``, so they stay symbolic under ONNX export;
    written as ``multiple * ceil(h / multiple) - h``, the padded size traces as a multiple of
    ``multiple`` and every pyramid level's size stays a short expression (a tenth faster to
    export than ``(-h) % multiple``).
    """
    h, w = x.shape[-2:]
    pad_h = (h + multiple - 1) // multiple * multiple - h
    pad_w = (w + multiple - 1) // multiple * multiple - w
    return F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")


class Spk2ImgNet(nn.Module):
    """Spike window -> intensity image, plus SALI's intermediate estimates.

    Args:
        config: the member's shape; :data:`~spk2img.model.config.PAPER` is the published net.
    """

    def __init__(self, config: Spk2ImgNetConfig) -> None:
        super().__init__()
        self.config = config
        c, stride = config.channels, config.feature_stride
        self.sali = LightInference(
            config.block_frames,
            config.sali_subwindows,
            config.sali_hidden,
            config.sali_attention_hidden,
            config.sali_stride,
        )
        folded = len(config.sali_subwindows) * stride**2  # SALI's estimates, pixel-unshuffled
        self.features = FeatureExtractor(folded, c, config.residual_blocks, config.convs_per_block)
        self.pyramid = FeaturePyramid(c, config.pyramid_levels)
        self.align = PCDAlignment(
            c, config.pyramid_levels, config.deformable_groups, config.offsets_read_motion
        )
        self.fusion = ReliabilityFusion(
            c, config.num_blocks, config.reliability_hidden, config.fusion_hidden, stride**2
        )
        self.detail = (
            DetailRefinement(
                config.num_blocks * len(config.sali_subwindows) * config.sali_stride**2,
                config.detail_hidden,
                config.sali_stride,
                config.detail_depth,
                config.feature_stride if config.detail_aligned else 0,
            )
            if config.detail_hidden
            else None
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
        s, pixels = cfg.sali_stride, cfg.sali_stride**2
        spikes = fold(pad_to_multiple(spikes, cfg.size_multiple), s)  # (b, t * s * s, hp/s, wp/s)

        # five 13-frame blocks at offsets 0, 7, 14, 21, 28 (each frame s * s channels),
        # folded into the batch
        blocks = torch.stack(
            [
                spikes[:, start * pixels : (start + cfg.block_frames) * pixels]
                for start in range(0, cfg.num_blocks * cfg.block_stride, cfg.block_stride)
            ],
            dim=1,
        ).flatten(0, 1)  # (b * blocks, block_frames * s * s, hp / s, wp / s)

        # SALI, features and pyramid, shared by the blocks; the blocks' motion
        weighted, estimates = self.sali(blocks)  # (b * blocks, n * s * s, hp / s, wp / s) each
        pyramid = [
            level.unflatten(0, (-1, cfg.num_blocks)) for level in self.block_pyramid(weighted)
        ]  # (b, blocks, c, h_l, w_l) per level
        weighted = weighted.unflatten(0, (-1, cfg.num_blocks))  # (b, blocks, n * s * s, ...)
        motion = self.block_motion(weighted)  # (b * neighbours, 2, h_f, w_f) or None

        # align each neighbour to the key, all neighbours in one batch
        neighbours = cfg.num_blocks - 1
        key_pyramid = [level[:, key] for level in pyramid]  # (b, c, h_l, w_l) per level
        aligned = self.align(
            [without_key(level, key).flatten(0, 1) for level in pyramid],
            [per_neighbour(level, neighbours) for level in key_pyramid],
            motion if cfg.flow_guided else None,
        ).unflatten(0, (-1, neighbours))  # (b, neighbours, c, h_f, w_f)

        # reliability fusion (and the detail of SALI's estimates) -> 0.6 * I
        pred = self.fuse(list(aligned.unbind(1)), key_pyramid[0], weighted, motion)
        image = to_intensity(pred, h, w, self.training)
        estimates = unfold(estimates, cfg.sali_stride).unflatten(0, (-1, cfg.num_blocks))
        estimates = estimates[..., :h, :w] / SPIKE_RATE
        return image, estimates

    def block_pyramid(self, weighted: torch.Tensor) -> list[torch.Tensor]:
        """SALI's weighted estimates (folded by the SALI stride) -> the feature pyramid, level 1
        first, ``(b, c, hp / (s * 2**(l-1)), wp / (s * 2**(l-1)))`` with ``s`` the feature
        stride."""
        cfg = self.config
        # refold at the feature stride (itself where the strides are equal): channels
        # estimate-major as fold() gives
        weighted = refold(weighted, cfg.sali_stride, cfg.feature_stride)
        return self.pyramid(self.features(weighted))

    def block_motion(self, weighted: torch.Tensor) -> torch.Tensor | None:
        """Every block's weighted SALI estimates ``(b, blocks, n * s * s, hp / s, wp / s)`` ->
        each neighbour's motion to the key at the feature stride ``(b * neighbours, 2, h_f,
        w_f)`` (:func:`~spk2img.model.motion.block_motion`), for members that align their
        detail refinement or their features by it (else None)."""
        cfg = self.config
        if not (cfg.detail_aligned or cfg.flow_guided):
            return None
        motion = block_motion(
            weighted,
            cfg.sali_stride,
            cfg.motion_scale,
            levels=cfg.motion_levels,
            window=cfg.motion_window,
            damping=cfg.motion_damping,
            damping_per_intensity=cfg.motion_damping_per_intensity,
            iterations=cfg.motion_iterations,
        )
        scale = cfg.motion_scale // cfg.feature_stride
        return motion if scale == 1 else upsample_flow(motion, scale)

    def fuse(
        self,
        aligned: list[torch.Tensor],
        key_feat: torch.Tensor,
        weighted: torch.Tensor | None,
        motion: torch.Tensor | None,
    ) -> torch.Tensor:
        """The aligned neighbours (temporal order) and the key's level-1 features, each
        ``(b, c, h_f, w_f)``, every block's weighted SALI estimates ``(b, blocks, n * s * s,
        hp / s, wp / s)`` and the neighbours' motion (:meth:`block_motion`; both read only by
        the detail refinement, None without one) -> the prediction of ``0.6 * I`` ``(b, 1,
        hp, wp)`` at full size."""
        pred = unfold(self.fusion(aligned, key_feat), self.config.feature_stride)
        return pred if self.detail is None else self.detail(pred, weighted, motion)


def to_intensity(pred: torch.Tensor, height: int, width: int, training: bool) -> torch.Tensor:
    """The head's padded ``0.6 * I`` ``(b, 1, hp, wp)`` -> ``I`` ``(b, 1, height, width)``,
    clipped to [0, 1] unless ``training``."""
    image = pred[..., :height, :width] / SPIKE_RATE
    return image if training else image.clamp(0, 1)


def build_model(member: str | Spk2ImgNetConfig) -> Spk2ImgNet:
    """A freshly initialised network for a member name (``paper``, ``small``, ...) or a config."""
    config = get_config(member) if isinstance(member, str) else member
    return Spk2ImgNet(config)
