"""The names of a block's code: what the block encoder hands the align-and-fuse head.

Pure Python (no torch), so that the runtime's ONNX block codec and the network's block split
(:mod:`spk2img.model.block_split`) name the same arrays.
"""

from __future__ import annotations

CODE_ROLES = ("feat", "nbr", "key")
"""A block code's parts per pyramid level: feature pyramid, offset-conv terms as a neighbour and
as the key."""

DETAIL_CODE = "sali"
"""The code's last part in members whose head reads the blocks' SALI estimates (a detail
refinement, or the blocks' motion guiding the alignment): the block's weighted SALI
estimates, which the head reads from every block."""


def reads_sali(detail_hidden: int, flow_guided: bool) -> bool:
    """Whether a member's head reads every block's weighted SALI estimates: with a detail
    refinement (``detail_hidden`` > 0) or an alignment its blocks' motion guides."""
    return detail_hidden > 0 or flow_guided


def code_names(levels: int, sali: bool = False) -> list[str]:
    """Names of a block code's arrays: ``feat_l1 .. feat_lL``, ``nbr_l1 ..``, ``key_l1 ..``,
    then ``sali`` where the head reads the SALI estimates (``sali``, :func:`reads_sali`)."""
    names = [f"{role}_l{i}" for role in CODE_ROLES for i in range(1, levels + 1)]
    return names + [DETAIL_CODE] if sali else names


def code_role(name: str) -> str:
    """The role of a code array (``feat``, ``nbr``, ``key`` or ``sali``) from its name."""
    return name.split("_")[0]


def role_blocks(num_blocks: int) -> dict[str, int | None]:
    """Blocks each code role stacks in the head's inputs: all of them, the neighbours
    (``num_blocks - 1``), or None: the key block's only, no axis."""
    return {"feat": num_blocks, "nbr": num_blocks - 1, "key": None, DETAIL_CODE: num_blocks}
