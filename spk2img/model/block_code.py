"""The names of a block's code: what the block encoder hands the align-and-fuse head.

Pure Python (no torch), so that the runtime's ONNX block codec and the network's block split
(:mod:`spk2img.model.block_split`) name the same arrays.
"""

from __future__ import annotations

CODE_ROLES = ("feat", "nbr", "key")
"""A block code's parts: feature pyramid, offset-conv terms as a neighbour and as the key."""


def code_names(levels: int) -> list[str]:
    """Names of a block code's arrays: ``feat_l1 .. feat_lL``, ``nbr_l1 ..``, ``key_l1 ..``."""
    return [f"{role}_l{i}" for role in CODE_ROLES for i in range(1, levels + 1)]
