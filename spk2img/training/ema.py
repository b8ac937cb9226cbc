"""An exponential moving average of a network's weights during training (``--ema-decay``): a
running "soup" of the recent steps' weights, which validation scores and ``best.pt`` keeps."""

from __future__ import annotations

import copy

import torch
from torch import nn


class WeightAverage:
    """``average = decay * average + (1 - decay) * weights`` after every optimiser step, for
    every floating-point parameter and buffer; integer buffers are copied. :attr:`model` is the
    averaged network (eval mode, no gradients), as wide and on the same device as the one it
    follows."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0 < decay < 1:
            raise ValueError(f"an average's decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.model = copy.deepcopy(model).eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average towards ``model``'s weights now (one step's share)."""
        current = model.state_dict()
        for name, average in self.model.state_dict().items():
            if average.is_floating_point():
                average.lerp_(current[name].to(average.dtype), 1 - self.decay)
            else:
                average.copy_(current[name])
