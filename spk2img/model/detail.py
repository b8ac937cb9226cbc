"""Full-resolution detail for members whose fusion runs at reduced size (not in the paper)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .sali import fold, unfold
from .warp import warp


class DetailRefinement(nn.Module):
    """Adds fine detail to a prediction made at ``1/feature_stride`` size from every block's
    SALI estimates: where the scene holds still their whole window sharpens the image, where
    it moves the key's own estimates do. With ``motion_channels``, the neighbours' estimates
    are first warped to the key (:meth:`align`) by a flow that a conv3x3 reads from the
    alignment's level-1 offset feature.

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
        motion_channels: channels of the alignment's offset feature that the flow is read
            from (0: the estimates are read unaligned).
        motion_stride: resolution step of that feature (the feature stride).
    """

    def __init__(
        self,
        estimates: int,
        hidden: int,
        stride: int,
        depth: int = 1,
        motion_channels: int = 0,
        motion_stride: int = 1,
    ) -> None:
        super().__init__()
        self.stride = stride
        self.motion_stride = motion_stride
        self.flow = nn.Conv2d(motion_channels, 2, 3, padding=1) if motion_channels else None
        if self.flow is not None:  # no motion until trained: the unaligned refinement
            nn.init.zeros_(self.flow.weight)
            nn.init.zeros_(self.flow.bias)
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
        hp / s, wp / s)`` (and, with a flow, the alignment's ``motion`` of each neighbour, see
        :meth:`align`) -> the refined ``(b, 1, hp, wp)``."""
        if self.flow is not None:
            estimates = self.align(estimates, motion)
        folded = fold(pred, self.stride)
        inputs = torch.cat([folded, estimates.flatten(1, 2)], dim=1)
        return unfold(folded + self.body(inputs), self.stride)

    def align(self, estimates: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        """Warp the neighbours' estimates to the key block.

        Args:
            estimates: ``(b, blocks, n * s * s, hp / s, wp / s)``, every block in temporal order.
            motion: ``(b * (blocks - 1), c, hp / f, wp / f)``, the alignment's level-1 offset
                feature of each neighbour in order (``f`` the motion stride).

        Returns:
            ``estimates`` with each neighbour's sampled at the flow read from its ``motion``
            (upsampled to full size, in full-size pixels), the key's as it was.
        """
        blocks, f, s = estimates.shape[1], self.motion_stride, self.stride
        key = blocks // 2
        flow = self.flow(motion) * f  # (b * neighbours, 2, hp / f, wp / f), full-size pixels
        if f > 1:
            flow = F.interpolate(flow, scale_factor=f, mode="bilinear", align_corners=False)
        neighbours = torch.cat([estimates[:, :key], estimates[:, key + 1 :]], dim=1)
        warped = fold(warp(unfold(neighbours.flatten(0, 1), s), flow), s)
        warped = warped.unflatten(0, (-1, blocks - 1))
        return torch.cat([warped[:, :key], estimates[:, key : key + 1], warped[:, key:]], dim=1)

    @torch.no_grad()
    def grow_from(self, state: dict[str, torch.Tensor]) -> None:
        """Load the weights of a narrower or shallower refinement (``state``: its
        ``body.<i>.weight`` and ``.bias``, and its ``flow.*`` if it has one) so that this one
        computes exactly what it did (a flow it lacked stays at zero: no motion).

        The old hidden channels come first; the new ones keep their fresh weights but reach
        the old channels and the output through zeros, and each hidden conv the old one lacked
        passes the old channels through (an identity kernel: a ReLU of a ReLU is itself), so
        training starts from the old refinement and grows into the new width and depth.
        Raises ``ValueError`` when ``state`` is wider or deeper than this module or reads
        other inputs.
        """
        if "flow.weight" in state:
            if self.flow is None:
                raise ValueError("the refinement's weights warp its inputs; this one does not")
            self.flow.load_state_dict({"weight": state["flow.weight"], "bias": state["flow.bias"]})
        convs = [layer for layer in self.body if isinstance(layer, nn.Conv2d)]
        indices = sorted({int(key.split(".")[1]) for key in state if key.startswith("body.")})
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
