"""A term of the training loss that teaches the alignment to follow motion (``--align-weight``).

The final image's loss reaches the offset predictors of the pyramid's coarse levels with
gradients that do not point along the motion (docs/motion_study.md): trained on it alone, the
shipped networks' deformable convs sample the same places whatever the content does. Training
knows the truth at every block's centre, so it can say where each neighbour's content is: an
aligning conv at pyramid level ``l`` samples the neighbour at ``p + d(p)``, ``d`` its mean offset
over taps and groups (the flow that guides it included); if it follows the motion, the
neighbour's truth sampled there is the key's truth. :func:`alignment_term` scores that, level
by level, on the truths averaged down to each level's size: an L1 difference in linear
intensity whose gradient points the offsets along the motion. It is zero for an alignment that
carries every neighbour onto the key, whatever the motion; at inference nothing changes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from spk2img.model.block_ops import per_neighbour, without_key
from spk2img.model.deform_conv import recorded_mean_shifts
from spk2img.model.network import Spk2ImgNet
from spk2img.model.warp import warp


def recorded_shifts(model: Spk2ImgNet):
    """A context inside which every forward pass of ``model`` records each pyramid level's
    aligning conv's mean sampling shift (:func:`~spk2img.model.deform_conv.recorded_mean_shifts`,
    with its gradient) into the yielded dict: ``{level: (b * neighbours, 2, h_l, w_l)}``,
    ``(dy, dx)`` in that level's feature pixels, the neighbours of each window in temporal
    order."""
    return recorded_mean_shifts(
        {int(name[1:]): conv for name, conv in model.align.dcn_pack.items()}
    )


def alignment_term(
    shifts: dict[int, torch.Tensor], truth: torch.Tensor, feature_stride: int
) -> torch.Tensor:
    """Mean over the levels of ``|truth_n(p + d(p)) - truth_k(p)|``.

    Args:
        shifts: :func:`recorded_shifts`' record of one forward pass (at least one level).
        truth: ``(b, blocks, h, w)`` linear intensity at the block centres (the key in the
            middle); ``h`` and ``w`` multiples of the coarsest level's scale.
        feature_stride: full-size pixels per level-1 feature pixel.

    Returns:
        A scalar: the mean absolute difference between each neighbour's truth, averaged down to
        a level's size and sampled at that level's mean shift, and the key's.
    """
    blocks = truth.shape[1]
    key, neighbours = blocks // 2, blocks - 1
    terms = []
    for level, shift in shifts.items():
        scale = feature_stride * 2 ** (level - 1)
        small = F.avg_pool2d(truth, scale)  # (b, blocks, h / scale, w / scale)
        h, w = small.shape[-2:]
        moved = without_key(small, key).flatten(0, 1).unsqueeze(1)  # (b * neighbours, 1, ...)
        target = per_neighbour(small[:, key], neighbours).unsqueeze(1)
        sampled = warp(moved, shift[..., :h, :w].float())
        terms.append((sampled - target).abs().mean())
    return torch.stack(terms).mean()
