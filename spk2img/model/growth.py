"""Grow a trained Spk2ImgNet into a wider and deeper member that computes exactly what it did.

A larger member trained from scratch needs many GPU sessions before it catches up with the
trained smaller one; grown from it, the larger member starts at the smaller one's quality and
every step of training goes to what the new channels and blocks add.

Widening: the old channels of every tensor come first (the first ``c`` channels of a
``c``-channel feature, each part of a concatenation at the start of its part, the old offset
groups at the start of the offsets and of the mask logits). The new output channels of each
conv keep the fresh network's weights, so they carry features from the first step; the old
output channels read them through zeros, so the old channels, and the image read from them,
are what the smaller network computed. The zeros get gradients at once (the new features are
not zero), so the new width starts to contribute after the first update.

Deepening: the feature extractor's new residual blocks, appended after the old ones, start with
their last conv at zero: ``relu(x + 0)`` is ``x`` for the non-negative features they receive.

Deformable groups keep their channel count (``channels / deformable_groups``), so every old
channel stays in its old offset group. SALI and the blocks' geometry do not change.

The detail refinement (members whose fusion runs at reduced size) may be added, widened,
deepened or aligned, and the blocks' motion may come to guide the alignment
(:meth:`~spk2img.model.detail.DetailRefinement.grow_from`): a refinement added or grown
starts adding nothing new, and the motion adds nothing on a still scene. The alignment's offset
features may come to read the motion (``offsets_read_motion``): those convs start at zero.
"""

from __future__ import annotations

import dataclasses
import re
from typing import TYPE_CHECKING

import torch
from torch import nn

from .config import MOTION_FIELDS, Spk2ImgNetConfig
from .deform_conv import ModulatedDeformConv2d

if TYPE_CHECKING:
    from .network import Spk2ImgNet

GROWN_FIELDS = ("channels", "deformable_groups", "reliability_hidden", "fusion_hidden")
"""Widths that may grow (none may shrink); ``residual_blocks`` may grow too."""

DETAIL_FIELDS = (
    "detail_hidden",
    "detail_depth",
    "detail_aligned",
    "flow_guided",
    "offsets_read_motion",
)
"""The detail refinement's shape and the motion's use, which may grow too."""

# the channel layout of each grown weight, (output, input), by parameter name; a layout names
# the widths whose tensors are concatenated along that axis: "c" the feature channels, "c*" as
# many feature tensors as the axis holds, "rh" / "fh" the reliability masks' and the fusion's
# hidden channels, "offsets" / "mask" a deformable conv's offset and mask-logit channels, and
# "=" an axis that does not grow. Biases take their weight's output layout.
LAYOUTS: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    (r"features\.head\.0", ("c",), ("=",)),
    (r"features\.body\.\d+\.body\.\d+", ("c",), ("c",)),
    (r"pyramid\.downsample\.\d+\.\d+", ("c",), ("c",)),
    (r"align\.(offset_conv[123]\.l\d+|feat_conv\.l\d+|cas_offset_conv[12])", ("c",), ("c*",)),
    (r"align\.(dcn_pack\.l\d+|cas_dcn_pack)", ("c",), ("c",)),
    (r"align\.(dcn_pack\.l\d+|cas_dcn_pack)\.conv_offset_mask", ("offsets", "mask"), ("c",)),
    (r"fusion\.masks\.\d+\.body\.0", ("rh",), ("c*",)),
    (r"fusion\.masks\.\d+\.body\.2", ("rh",), ("rh",)),
    (r"fusion\.masks\.\d+\.body\.4", ("c",), ("rh",)),
    (r"fusion\.reconstruct\.0", ("fh",), ("c*",)),
    (r"fusion\.reconstruct\.2", ("c",), ("fh",)),
    (r"fusion\.reconstruct\.4", ("=",), ("c",)),
)


def growth_problems(stored: Spk2ImgNetConfig, config: Spk2ImgNetConfig) -> list[str]:
    """Why ``stored`` cannot grow into ``config`` (empty where it can, or where they are equal):
    only :data:`GROWN_FIELDS`, ``residual_blocks``, :data:`DETAIL_FIELDS` and
    :data:`MOTION_FIELDS` may differ, none may shrink, and a deformable group keeps its
    channel count."""
    grown = (*GROWN_FIELDS, "residual_blocks")
    changed = [
        f"{field.name} {getattr(stored, field.name)} -> {getattr(config, field.name)}"
        for field in dataclasses.fields(config)
        if field.name not in (*grown, *DETAIL_FIELDS, *MOTION_FIELDS)
        and getattr(config, field.name) != getattr(stored, field.name)
    ]
    problems = []
    if changed:
        problems.append(
            "only the widths, residual_blocks and the detail refinement can grow "
            f"({', '.join(changed)})"
        )
    shrunk = [name for name in grown if getattr(config, name) < getattr(stored, name)]
    if shrunk:
        problems.append(f"{', '.join(shrunk)} would shrink")
    problems += _detail_problems(stored, config)
    if config.channels * stored.deformable_groups != stored.channels * config.deformable_groups:
        problems.append(
            "channels per deformable group change "
            f"({stored.channels}/{stored.deformable_groups} -> "
            f"{config.channels}/{config.deformable_groups})"
        )
    return problems


def _detail_problems(stored: Spk2ImgNetConfig, config: Spk2ImgNetConfig) -> list[str]:
    """Why ``stored``'s detail refinement and use of motion cannot grow into ``config``'s: the
    refinement may be added, widened, deepened and aligned, and the motion may come to guide
    the alignment, none of them undone."""
    if stored.detail_hidden and not config.detail_hidden:
        return ["the detail refinement would be removed"]
    undone = [
        name
        for name in ("detail_hidden", "detail_aligned", "flow_guided", "offsets_read_motion")
        if getattr(config, name) < getattr(stored, name)
    ]
    if stored.detail_hidden and config.detail_depth < stored.detail_depth:
        undone.append("detail_depth")
    return [f"{', '.join(undone)} would shrink"] if undone else []


@torch.no_grad()
def grow_weights(
    model: Spk2ImgNet, weights: dict[str, torch.Tensor], stored: Spk2ImgNetConfig
) -> None:
    """Load the weights ``weights`` of a network of config ``stored`` into ``model``, a freshly
    initialised network it grows into (:func:`growth_problems` names nothing), so that ``model``
    computes what the stored network did (module docstring). Raises ``ValueError`` naming what
    does not fit."""
    config = model.config
    problems = growth_problems(stored, config)
    if problems:
        raise ValueError("; ".join(problems))
    own = model.state_dict()
    unknown = sorted(set(weights) - set(own))
    if unknown:
        raise ValueError(f"weights the grown network lacks: {', '.join(unknown[:3])}")
    detail = {k.removeprefix("detail."): v for k, v in weights.items() if k.startswith("detail.")}
    if stored.detail_hidden and not detail:
        raise ValueError("no stored weights for the detail refinement")
    if detail:
        try:
            model.detail.grow_from(detail)
        except (KeyError, ValueError, RuntimeError) as exc:
            raise ValueError(f"the detail refinement does not fit: {exc}") from exc
    for name, target in own.items():
        if name.startswith("detail."):
            continue  # grown above, or added: it starts adding nothing (its last conv is zero)
        block = re.fullmatch(r"features\.body\.(\d+)\.body\.\d+\.(weight|bias)", name)
        added = (block and int(block[1]) >= stored.residual_blocks) or (
            name.startswith("align.motion_conv.") and not stored.offsets_read_motion
        )  # an added residual block or motion conv starts as initialised (zeroed below, or zero)
        if name in weights:
            _place(name, target, weights[name], stored, config)
        elif not added:
            raise ValueError(f"no stored weights for {name}")
    last = f"body.{2 * (config.convs_per_block - 1)}"  # the last conv of a residual block
    for block in list(model.features.body)[stored.residual_blocks :]:
        nn.init.zeros_(block.get_submodule(last).weight)
        nn.init.zeros_(block.get_submodule(last).bias)


def _place(
    name: str,
    target: torch.Tensor,
    old: torch.Tensor,
    stored: Spk2ImgNetConfig,
    config: Spk2ImgNetConfig,
) -> None:
    """Write one stored tensor into its place in the grown network's ``target`` (in place)."""
    if old.shape == target.shape:
        target.copy_(old)
        return
    layout = _layout(name)
    if layout is None:
        raise ValueError(f"{name}: {tuple(old.shape)} cannot grow into {tuple(target.shape)}")
    if old.dim() not in (1, 4):
        raise ValueError(f"{name}: a {old.dim()}-d tensor does not grow")
    out_layout, in_layout = layout
    rows = _positions(name, out_layout, old.shape[0], stored, config).to(target.device)
    if old.dim() == 1:  # a bias
        target[rows] = old.to(target)
        return
    cols = _positions(name, in_layout, old.shape[1], stored, config).to(target.device)
    new_inputs = torch.ones(target.shape[1], dtype=torch.bool, device=target.device)
    new_inputs[cols] = False
    target[rows[:, None], cols] = old.to(target)
    target[rows[:, None], new_inputs.nonzero()[:, 0]] = 0.0  # old outputs ignore new inputs


def _layout(name: str) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
    module = name.rsplit(".", 1)[0]
    for pattern, out_layout, in_layout in LAYOUTS:
        if re.fullmatch(pattern, module):
            return out_layout, in_layout
    return None


def _positions(
    name: str,
    layout: tuple[str, ...],
    size: int,
    stored: Spk2ImgNetConfig,
    config: Spk2ImgNetConfig,
) -> torch.Tensor:
    """Where the ``size`` stored channels of an axis with ``layout`` go in the grown axis."""
    if layout == ("c*",):
        if size % stored.channels:
            raise ValueError(f"{name}: {size} channels are not whole feature tensors")
        layout = ("c",) * (size // stored.channels)
    positions, start = [], 0
    for part in layout:
        old_width, new_width = (
            (size, size) if part == "=" else (_width(part, stored), _width(part, config))
        )
        positions.append(torch.arange(start, start + old_width))
        start += new_width
    found = torch.cat(positions)
    if len(found) != size:
        raise ValueError(f"{name}: {size} channels do not have the layout {layout}")
    return found


def _width(part: str, config: Spk2ImgNetConfig) -> int:
    taps = ModulatedDeformConv2d.kernel_size**2  # offsets: (dy, dx) a tap; mask logits: one
    return {
        "c": config.channels,
        "rh": config.reliability_hidden,
        "fh": config.fusion_hidden,
        "offsets": 2 * taps * config.deformable_groups,
        "mask": taps * config.deformable_groups,
    }[part]
