"""Full-resolution detail for members whose fusion runs at reduced size (not in the paper)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .block_ops import without_key
from .sali import fold, unfold
from .warp import warp

MOTION_DEADBAND = 0.5
"""Pixels (full size) taken off each component of the blocks' flow before warping: on still
scenes the noise of 13-frame estimates gives flows of 0.1-0.4 px that move nothing but blur
the neighbours' detail in bilinear sampling."""


class DetailRefinement(nn.Module):
    """Adds fine detail to a prediction made at ``1/feature_stride`` size from every block's
    SALI estimates: where the scene holds still their whole window sharpens the image, where
    it moves the key's own estimates do. With ``motion_stride``, the neighbours' estimates
    are first warped to the key (:meth:`align`) by their motion
    (:func:`~spk2img.model.motion.block_motion`, at ``1/motion_stride`` of the size).

    At SALI's resolution step ``s``: conv3x3 on ``[prediction folded s x s, the blocks'
    attention-weighted SALI estimates]`` -> ``hidden``, ReLU, ``depth - 1`` times conv3x3
    ``hidden -> hidden``, ReLU, then conv3x3 -> ``s * s``, added to the folded prediction and
    unfolded. The last conv starts at zero, so a network grown by this module starts out as the
    one it grew from.

    Args:
        estimates: channels of the blocks' weighted estimates (``blocks * n * s * s`` for ``n``
            sub-windows).
        hidden: hidden channels.
        stride: SALI's resolution step ``s``.
        depth: hidden convs (each followed by a ReLU).
        motion_stride: resolution step of the blocks' motion (a multiple of ``stride``; 0:
            the estimates are read unaligned).
    """

    def __init__(
        self,
        estimates: int,
        hidden: int,
        stride: int,
        depth: int = 1,
        motion_stride: int = 0,
    ) -> None:
        super().__init__()
        if motion_stride % stride:
            raise ValueError(f"motion_stride={motion_stride} must be a multiple of {stride}")
        self.stride = stride
        self.motion_stride = motion_stride
        pixels = stride**2
        layers: list[nn.Module] = [nn.Conv2d(estimates + pixels, hidden, 3, padding=1), nn.ReLU()]
        for _ in range(depth - 1):
            layers += [nn.Conv2d(hidden, hidden, 3, padding=1), nn.ReLU()]
        layers.append(nn.Conv2d(hidden, pixels, 3, padding=1))
        self.body = nn.Sequential(*layers)
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)

    def forward(
        self, pred: torch.Tensor, estimates: torch.Tensor, motion: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``pred`` ``(b, 1, hp, wp)`` and the blocks' ``estimates`` ``(b, blocks, n * s * s,
        hp / s, wp / s)`` (and, with a motion stride, their ``motion``: see :meth:`align`) ->
        the refined ``(b, 1, hp, wp)``."""
        if self.motion_stride:
            estimates = self.align(estimates, motion)
        folded = fold(pred, self.stride)
        inputs = torch.cat([folded, estimates.flatten(1, 2)], dim=1)
        return unfold(folded + self.body(inputs), self.stride)

    def align(self, estimates: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        """Warp the neighbours' estimates to the key block: by their motion less
        :data:`MOTION_DEADBAND`, upsampled to full size, at full size.

        Args:
            estimates: ``(b, blocks, n * s * s, hp / s, wp / s)``, every block in temporal order.
            motion: ``(b * (blocks - 1), 2, hp / f, wp / f)``, each neighbour's motion in pixels
                of ``1/f`` size (``f`` the motion stride;
                :func:`~spk2img.model.motion.block_motion`).

        Returns:
            The same, each neighbour's estimates sampled where its motion points, the key's as
            they were.
        """
        blocks, f, s = estimates.shape[1], self.motion_stride, self.stride
        key = blocks // 2
        flow = motion * f  # full-size pixels
        flow = flow - flow.clamp(-MOTION_DEADBAND, MOTION_DEADBAND)
        flow = F.interpolate(flow, scale_factor=f, mode="bilinear", align_corners=False)
        neighbours = without_key(estimates, key)
        warped = fold(warp(unfold(neighbours.flatten(0, 1), s), flow), s)
        warped = warped.unflatten(0, (-1, blocks - 1))
        return torch.cat([warped[:, :key], estimates[:, key : key + 1], warped[:, key:]], dim=1)

    @torch.no_grad()
    def grow_from(self, state: dict[str, torch.Tensor]) -> None:
        """Load the weights of a narrower or shallower refinement (``state``: its
        ``body.<i>.weight`` and ``.bias``) so that this one computes exactly what it did (the
        same inputs: an aligned refinement grown from an unaligned one reads them warped).

        The old hidden channels come first; the new ones keep their fresh weights but reach
        the old channels and the output through zeros, and each hidden conv the old one lacked
        passes the old channels through (an identity kernel: a ReLU of a ReLU is itself), so
        training starts from the old refinement and grows into the new width and depth.
        Raises ``ValueError`` when ``state`` is wider or deeper than this module or reads
        other inputs.
        """
        convs = [layer for layer in self.body if isinstance(layer, nn.Conv2d)]
        indices = sorted({int(key.split(".")[1]) for key in state})
        old = [(state[f"body.{i}.weight"], state[f"body.{i}.bias"]) for i in indices]
        hidden = old[0][0].shape[0]
        if (
            len(old) > len(convs)
            or hidden > convs[0].out_channels
            or old[0][0].shape[1:] != convs[0].weight.shape[1:]
            or old[-1][0].shape[0] != convs[-1].out_channels
        ):
            raise ValueError("the refinement's weights are wider or deeper than this one")
        (first, last), (old_first, old_last) = (convs[0], convs[-1]), (old[0], old[-1])
        first.weight[:hidden], first.bias[:hidden] = old_first
        for i, conv in enumerate(convs[1:-1], start=1):
            conv.weight[:hidden] = 0.0
            if i < len(old) - 1:
                conv.weight[:hidden, :hidden], conv.bias[:hidden] = old[i]
            else:
                conv.weight[range(hidden), range(hidden), 1, 1] = 1.0
                conv.bias[:hidden] = 0.0
        last.weight.zero_()
        last.weight[:, :hidden], last.bias[:] = old_last
