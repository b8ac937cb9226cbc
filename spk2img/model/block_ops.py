"""The key block and its neighbours in a ``(b, blocks, ...)`` stack."""

from __future__ import annotations

import torch


def per_neighbour(tensor: torch.Tensor, neighbours: int) -> torch.Tensor:
    """The key's ``(b, ...)`` repeated for each of its neighbours: ``(b * neighbours, ...)``."""
    return tensor.unsqueeze(1).expand(-1, neighbours, *tensor.shape[1:]).flatten(0, 1)


def without_key(level: torch.Tensor, key: int) -> torch.Tensor:
    """``(b, blocks, ...)`` -> ``(b, blocks - 1, ...)``: the neighbours, in temporal order."""
    return torch.cat([level[:, :key], level[:, key + 1 :]], dim=1)
