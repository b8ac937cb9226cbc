"""Spk2ImgNet hyper-parameters and the named family members built from them.

``paper`` is the published network (docs/architecture.md, 3,904,185 parameters); smaller
members keep every idea of it (SALI, pyramid deformable alignment, reliability fusion) at lower
width, depth or resolution.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Geometry:
    """Which spike frames a network reads and how they split into blocks: all the runtime, the
    evaluation and the service need to know of a model (in torch from its config, in ONNX from
    the graph's ``config`` metadata, :meth:`from_metadata`).

    A window of :attr:`window_frames` frames (odd) is centred on the output frame ``k``: frames
    ``k - half .. k + half``. Its :attr:`num_blocks` blocks of :attr:`block_frames` frames start
    every :attr:`block_stride` frames; the middle block is the key.
    """

    block_frames: int
    """Frames of one temporal block (13 as published)."""
    block_stride: int
    """Frames between the starts of consecutive blocks (7 as published)."""
    num_blocks: int
    """Temporal blocks of a window (odd; 5 as published)."""
    size_multiple: int = 1
    """Height and width are padded to a multiple of this inside the network."""

    def __post_init__(self) -> None:
        if min(self.block_frames, self.block_stride, self.num_blocks, self.size_multiple) < 1:
            raise ValueError(f"a geometry's sizes must be positive, got {self}")
        if self.num_blocks % 2 != 1 or self.block_frames % 2 != 1:
            raise ValueError(f"blocks and their frames must be odd in number, got {self}")

    @property
    def window_frames(self) -> int:
        """Spike frames the network reads, centred on the output frame (41 as published)."""
        return (self.num_blocks - 1) * self.block_stride + self.block_frames

    @property
    def half(self) -> int:
        """Frames on each side of the centre: the first valid centre of a stream (20)."""
        return self.window_frames // 2

    @property
    def block_starts(self) -> tuple[int, ...]:
        """Each block's first frame relative to the centre (-20, -13, -6, 1, 8 as published)."""
        return tuple(self.block_stride * i - self.half for i in range(self.num_blocks))

    @property
    def block_centres(self) -> tuple[int, ...]:
        """Each block's middle frame within the window (6, 13, 20, 27, 34 as published): the
        frames the ground truth of training is taken at."""
        return tuple(s + self.half + self.block_frames // 2 for s in self.block_starts)

    def padded_size(self, height: int, width: int) -> tuple[int, int]:
        """The ``(height, width)`` the network computes a frame at: both sides padded up to a
        multiple of :attr:`size_multiple` (``pad_to_multiple`` in the network)."""
        m = self.size_multiple
        return -(-height // m) * m, -(-width // m) * m

    def crop(self, windows, axis: int = 0):
        """The centred :attr:`window_frames` of longer windows whose frames run along ``axis``
        (an array; a window of the right length is returned as it is); a shorter or
        off-centre window raises ``ValueError``."""
        frames = windows.shape[axis]
        extra = frames - self.window_frames
        if extra < 0 or extra % 2:
            raise ValueError(f"a {frames}-frame window has no centred {self.window_frames} frames")
        index = [slice(None)] * windows.ndim
        index[axis] = slice(extra // 2, extra // 2 + self.window_frames)
        return windows[tuple(index)]

    def as_dict(self) -> dict[str, int]:
        """The geometry as JSON-ready numbers, ``window_frames`` included."""
        return {
            "window_frames": self.window_frames,
            "block_frames": self.block_frames,
            "block_stride": self.block_stride,
            "num_blocks": self.num_blocks,
            "size_multiple": self.size_multiple,
        }

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str]) -> Geometry:
        """The geometry an exported graph records: its ``config`` metadata (the network's
        :class:`Spk2ImgNetConfig` as JSON, spk2img.export.metadata); ``ValueError`` when absent."""
        if "config" not in metadata:
            raise ValueError("the graph carries no 'config' metadata: export it with spk2img")
        config = json.loads(metadata["config"])
        levels, stride = int(config["pyramid_levels"]), int(config.get("feature_stride", 1))
        return cls(
            block_frames=int(config["block_frames"]),
            block_stride=int(config["block_stride"]),
            num_blocks=int(config["num_blocks"]),
            size_multiple=stride * 2 ** (levels - 1),
        )


@dataclass(frozen=True)
class Spk2ImgNetConfig:
    """Shape of a Spk2ImgNet; the defaults are the published network (docs/architecture.md)."""

    block_frames: int = 13
    """Frames of one temporal block (the key block is centred on the window's centre)."""
    block_stride: int = 7
    """Frames between the starts of consecutive blocks."""
    num_blocks: int = 5
    """Temporal blocks (odd); the middle one is the key, the others are aligned to it."""
    sali_subwindows: tuple[int, ...] = (13, 11, 9, 7)
    """Lengths of the centred sub-windows of a block, one intensity estimate each (SALI)."""
    sali_hidden: int = 16
    """Channels of the hidden 3x3 conv of each SALI sub-window branch."""
    sali_attention_hidden: int = 8
    """Hidden channels of SALI's attention over the estimates (twice their number as published)."""
    sali_stride: int = 1
    """Resolution step of SALI: 1 as published; ``s > 1`` folds each ``s x s`` patch of the
    spike frames into channels (pixel unshuffle), so SALI's wide convs run at ``1/s`` of the size
    and write the ``s * s`` pixels of each estimate as channels. Must divide ``feature_stride``."""
    channels: int = 64
    """Feature channels of the extractor, the alignment and the reliability masks' output."""
    residual_blocks: int = 10
    """Residual blocks of the feature extractor."""
    convs_per_block: int = 3
    """3x3 convs per residual block (10 x 3 = 30 as published; the paper text says 15 blocks)."""
    pyramid_levels: int = 3
    """Levels of the alignment pyramid (full, 1/2, 1/4 ...); inputs are padded to 2**(levels-1)."""
    deformable_groups: int = 8
    """Offset groups of every modulated deformable conv; must divide ``channels``."""
    reliability_hidden: int = 64
    """Hidden channels of each neighbour's reliability-mask branch."""
    fusion_hidden: int = 192
    """Channels of the first fusion conv (``5 * channels -> fusion_hidden -> channels -> 1``)."""
    feature_stride: int = 1
    """Resolution step of the features, the alignment and the fusion: 1 as published (all at
    full size); ``s > 1`` folds each ``s x s`` patch of SALI's estimates into channels (pixel
    unshuffle), runs everything after SALI at ``1/s`` of the size and unfolds the fusion's
    ``s * s`` output channels into the full-size image (pixel shuffle)."""
    detail_hidden: int = 0
    """Hidden channels of the detail refinement (not in the paper; 0: none, as published): after
    a reduced-size fusion, ``detail_depth + 1`` 3x3 convs at SALI's resolution step add detail
    from every block's SALI estimates to the image (:mod:`spk2img.model.detail`)."""
    detail_depth: int = 1
    """Hidden 3x3 convs of the detail refinement (1: ``in -> hidden -> s * s``)."""
    detail_aligned: bool = False
    """The detail refinement warps the neighbours' SALI estimates to the key first, by the
    Lucas-Kanade flow between the blocks' intensities at the feature stride (no weights;
    False: read unaligned)."""
    flow_guided: bool = False
    """The blocks' motion (the one that aligns the detail refinement, where there is one) guides
    the alignment: each pyramid level's deformable conv adds it to its offsets, which then learn
    what is left of the motion (flow-guided deformable alignment, as in BasicVSR++; not in the
    paper). No weights: a checkpoint trained without it loads with it."""
    offsets_read_motion: bool = False
    """Each pyramid level's offset feature also reads the blocks' motion (needs
    ``flow_guided``), through a 3x3 conv per level that starts at zero (as BasicVSR++'s offset
    convs read the flow): the offsets can then learn a gain on a guide that finds part of the
    motion, which they cannot read from the features alone (docs/architecture.md, "Teaching
    the alignment"). Adds ``levels * (18 * channels + channels)`` weights; a checkpoint without
    them grows into it unchanged (:mod:`spk2img.model.growth`)."""
    motion_levels: int = 1
    """Pyramid levels of the blocks' Lucas-Kanade motion (coarse to fine, each half the size
    of the one below; :func:`~spk2img.model.motion.block_motion`), for members with
    ``detail_aligned`` or ``flow_guided``: ``2**(levels-1)`` times larger motion is followed."""
    motion_window: int = 5
    """Odd side, in pixels of the motion's resolution (``motion_stride``; the feature stride
    by default), of the neighbourhood each Lucas-Kanade system sums over."""
    motion_damping: float = 1e-3
    """Constant damping of each Lucas-Kanade system (squared intensity of SALI's estimates per
    pixel; ``spk2img.model.motion.MOTION_DAMPING``)."""
    motion_damping_per_intensity: float = 0.0
    """Damping per unit of the neighbourhood's mean intensity, which grows with the light as a
    spike count's noise does."""
    motion_iterations: int = 3
    """Gauss-Newton steps of the Lucas-Kanade motion at each pyramid level."""
    motion_stride: int = 0
    """Resolution step of the blocks' motion, a multiple of ``feature_stride`` (0: the feature
    stride): a full-size member's motion found at 1/4 of its size, over four times the
    displacement per window pixel and from 16 pixels' spikes each, then upsampled to it."""

    def __post_init__(self) -> None:
        if self.num_blocks % 2 != 1:
            raise ValueError(f"num_blocks must be odd, got {self.num_blocks}")
        for length in self.sali_subwindows:
            if not 0 < length <= self.block_frames or (self.block_frames - length) % 2:
                raise ValueError(
                    f"SALI sub-window {length} cannot be centred in a {self.block_frames}-frame "
                    "block"
                )
        if self.channels % self.deformable_groups:
            raise ValueError(
                f"deformable_groups={self.deformable_groups} must divide channels={self.channels}"
            )
        if self.pyramid_levels < 1:
            raise ValueError(f"pyramid_levels must be >= 1, got {self.pyramid_levels}")
        if self.feature_stride < 1:
            raise ValueError(f"feature_stride must be >= 1, got {self.feature_stride}")
        if self.detail_hidden < 0:
            raise ValueError(f"detail_hidden must be >= 0, got {self.detail_hidden}")
        if self.detail_depth < 1:
            raise ValueError(f"detail_depth must be >= 1, got {self.detail_depth}")
        if self.detail_aligned and not self.detail_hidden:
            raise ValueError("detail_aligned needs a detail refinement (detail_hidden > 0)")
        if self.offsets_read_motion and not self.flow_guided:
            raise ValueError("offsets_read_motion needs the motion to guide them (flow_guided)")
        if not 1 <= self.motion_levels <= self.pyramid_levels:
            raise ValueError(
                f"motion_levels must be 1 .. pyramid_levels={self.pyramid_levels}, "
                f"got {self.motion_levels}"
            )
        if self.motion_stride < 0 or self.motion_stride % self.feature_stride:
            raise ValueError(
                f"motion_stride must be 0 or a multiple of feature_stride={self.feature_stride}, "
                f"got {self.motion_stride}"
            )
        if self.motion_window < 1 or self.motion_window % 2 != 1 or self.motion_iterations < 1:
            raise ValueError(
                "motion_window must be odd and motion_iterations positive, got "
                f"{self.motion_window} and {self.motion_iterations}"
            )
        if min(self.motion_damping, self.motion_damping_per_intensity) < 0 or not (
            self.motion_damping or self.motion_damping_per_intensity
        ):
            raise ValueError("the motion's damping must be >= 0 and not all zero")
        if self.sali_stride < 1 or self.feature_stride % self.sali_stride:
            raise ValueError(
                f"sali_stride={self.sali_stride} must divide feature_stride={self.feature_stride}"
            )
        self.geometry  # noqa: B018 (checks that the blocks make a centred window)

    @property
    def geometry(self) -> Geometry:
        """The frames the network reads and their blocks (:class:`Geometry`)."""
        return Geometry(self.block_frames, self.block_stride, self.num_blocks, self.size_multiple)

    @property
    def window_frames(self) -> int:
        """Spike frames the network reads (41 as published, centred on the output frame)."""
        return self.geometry.window_frames

    @property
    def motion_scale(self) -> int:
        """Resolution step of the blocks' motion (``motion_stride``, 0: the feature stride)."""
        return self.motion_stride or self.feature_stride

    @property
    def size_multiple(self) -> int:
        """Height and width are padded to a multiple of this for the feature stride and the
        alignment pyramid (and the blocks' motion pyramid, for members that read it)."""
        pyramid = self.feature_stride * 2 ** (self.pyramid_levels - 1)
        if not (self.detail_aligned or self.flow_guided):
            return pyramid
        return math.lcm(pyramid, self.motion_scale * 2 ** (self.motion_levels - 1))


PAPER = Spk2ImgNetConfig()

PUBLISHED_GEOMETRY = PAPER.geometry
"""The published window (41 frames, five 13-frame blocks 7 apart), shared by every shipped model:
the length the simulated evaluation sets are filmed at and TFP's default window. A model with a
shorter window reads their centred crop (:meth:`Geometry.crop`)."""

SMALL = replace(
    PAPER,
    channels=24,
    residual_blocks=4,
    deformable_groups=4,
    reliability_hidden=24,
    fusion_hidden=72,
)

MEMBERS: dict[str, Spk2ImgNetConfig] = {
    "paper": PAPER,
    "medium": replace(
        SMALL, channels=48, deformable_groups=8, reliability_hidden=48, fusion_hidden=144
    ),
    "small": SMALL,
    "lite": replace(
        PAPER,
        channels=24,
        residual_blocks=4,
        convs_per_block=2,
        deformable_groups=2,
        reliability_hidden=24,
        fusion_hidden=64,
        feature_stride=2,
    ),
    "cpu": replace(
        PAPER,
        sali_stride=2,
        channels=32,
        residual_blocks=4,
        convs_per_block=2,
        deformable_groups=2,
        reliability_hidden=32,
        fusion_hidden=64,
        feature_stride=4,
        detail_hidden=48,
        detail_depth=2,
        detail_aligned=True,
        flow_guided=True,
    ),
    "tiny": replace(
        PAPER,
        sali_hidden=8,
        channels=12,
        residual_blocks=2,
        convs_per_block=2,
        pyramid_levels=2,
        deformable_groups=2,
        reliability_hidden=8,
        fusion_hidden=16,
    ),
}
"""The named family members, largest first: ``paper`` (3.90 M parameters), ``medium`` (1.92 M,
``small`` twice as wide: grown from a trained ``small`` it starts as that network,
:mod:`spk2img.model.growth`), ``small`` (0.49 M,
the paper's width ratios at 24 channels), ``lite`` (0.41 M, 24 channels at half resolution
after SALI: a quarter of ``small``'s cost), ``cpu`` (0.76 M, built for CPUs: SALI on 2x2 patches
folded into channels, 32 channels at a quarter of the size after it, a detail refinement of
two 48-channel convs at half size on the blocks' estimates warped to the key; 14.1 G MACs, the
least of all), ``tiny`` (74 k, 12 channels, a 2-level pyramid)."""


MOTION_FIELDS = (
    "motion_levels",
    "motion_window",
    "motion_damping",
    "motion_damping_per_intensity",
    "motion_iterations",
    "motion_stride",
)
"""The Lucas-Kanade motion's settings: no weights, so they may change freely (every weight is
loaded as stored; the motion it reads is another)."""


MOTION_SETTINGS = {"guided": "flow_guided", "read": "offsets_read_motion"} | {
    name.removeprefix("motion_"): name for name in MOTION_FIELDS
}
"""The names :func:`with_motion` takes -> the config's fields they set: whether the motion
guides the alignment (``guided``, 0 or 1), whether the offset convs read it too (``read``, 0 or
1: the only one with weights, which start at zero), and its weight-free settings."""


def with_motion(config: Spk2ImgNetConfig, settings: str) -> Spk2ImgNetConfig:
    """``config`` with the motion settings ``settings`` over its own: comma-separated
    ``NAME=VALUE`` pairs of :data:`MOTION_SETTINGS` (``""``: ``config`` as it is), e.g.
    ``guided=1,levels=3,window=15,damping=1e-4,damping_per_intensity=1e-3``. None of them but
    ``read`` has weights, so a checkpoint of ``config`` loads into the result as it is; with
    ``read=1`` it grows into it (the new convs start at zero: :mod:`spk2img.model.growth`).

    Raises ``ValueError`` naming what is wrong: an unknown name, a value that is not of the
    field's type (an integer, a number, 0 or 1), or settings the config refuses
    (:class:`Spk2ImgNetConfig`)."""
    changes: dict[str, bool | int | float] = {}
    for pair in filter(None, (p.strip() for p in settings.split(","))):
        name, sep, value = (part.strip() for part in pair.partition("="))
        if not sep or name not in MOTION_SETTINGS:
            names = ", ".join(MOTION_SETTINGS)
            raise ValueError(f"motion setting {pair!r}: use NAME=VALUE with NAME one of {names}")
        field_name = MOTION_SETTINGS[name]
        kind = type(getattr(config, field_name))
        wanted = {bool: "0 or 1", int: "an integer"}.get(kind, "a number")
        try:
            if kind is bool and value not in ("0", "1"):
                raise ValueError(value)
            changes[field_name] = bool(int(value)) if kind is bool else kind(value)
        except ValueError:
            raise ValueError(f"motion setting {pair!r}: {value!r} is not {wanted}") from None
    return replace(config, **changes)


def get_config(name: str) -> Spk2ImgNetConfig:
    """The config of member ``name`` (one of :data:`MEMBERS`)."""
    try:
        return MEMBERS[name]
    except KeyError:
        raise ValueError(f"unknown model {name!r}; choose one of {', '.join(MEMBERS)}") from None
