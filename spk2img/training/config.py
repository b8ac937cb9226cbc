"""What one training run is: :class:`TrainConfig`, whose every field is a ``spk2img train`` flag
with its help, default and choices (pure Python: the command line reads it without torch)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from spk2img.model.config import MEMBERS, with_motion

FINAL_TERMS = ("l1", "psnr")
"""The final image's term of the hierarchical loss (``--loss``)."""
DEVICES = ("cpu", "cuda")
"""Where a run trains (``--device``)."""
SYNTHESES = ("auto", "numpy", "torch")
"""Who films the training windows (``--synthesis``)."""
PRECISIONS = ("auto", "fp32", "bf16")
"""The arithmetic of the training steps (``--precision``)."""


def check_final_term(final: str) -> None:
    """``ValueError`` unless ``final`` is one of :data:`FINAL_TERMS` (``spk2img train --loss``)."""
    if final not in FINAL_TERMS:
        raise ValueError(f"--loss {final}: use one of {', '.join(FINAL_TERMS)}")


AT_LEAST = {
    "steps": 1,
    "batch_size": 1,
    "patch": 4,
    "warmup_steps": 0,
    "workers": 0,
    "val_every": 1,
    "val_per_class": 1,
    "checkpoint_every": 1,
    "threads": 1,
    "log_every": 1,
}
"""The least value of each integer flag of :class:`TrainConfig`."""


def check_share(flag_name: str, share: float) -> None:
    """``ValueError`` naming ``--flag-name`` unless ``share`` (of the samples) is in [0, 1]."""
    if not 0 <= share <= 1:
        raise ValueError(f"--{flag_name.replace('_', '-')} {share}: a share must be in [0, 1]")


def flag(default: Any, help: str, choices: tuple[str, ...] | None = None) -> Any:
    """A :class:`TrainConfig` field with its command-line ``help`` and ``choices``."""
    return field(default=default, metadata={"help": help, "choices": choices})


@dataclass
class TrainConfig:
    """One training run; every field is a ``spk2img train`` flag of the same name (its help in
    the field's metadata)."""

    member: str = flag("tiny", "family member to train", tuple(MEMBERS))
    run_dir: str = flag(
        "runs/default", "where last.pt, best.pt and metrics.jsonl go; a last.pt there is resumed"
    )
    steps: int = flag(20_000, "optimiser steps in all (a resumed run continues up to this)")
    batch_size: int = flag(8, "windows per step and per process")
    patch: int = flag(64, "side of the square training patches in pixels (a multiple of 4)")
    lr: float = flag(
        5e-4,
        "peak Adam learning rate, after a linear warm-up; a cosine decays it to 2 percent of it",
    )
    warmup_steps: int = flag(200, "steps of the learning rate's linear warm-up")
    loss: str = flag(
        "l1",
        "the final image's term of the hierarchical loss: l1, the paper's; psnr, minus the "
        "windows' mean PSNR (a last fine-tune of a trained model)",
        FINAL_TERMS,
    )
    seed: int = flag(0, "seed of the initial weights and of every batch")
    data: list[str] = field(default_factory=list, metadata={"help": "", "choices": None})
    """Folders of photographs and clips (:mod:`spk2img.sim.sources`; the ``--data`` flag, given
    once per folder); none: procedural content only. The held-out sources of the natural and
    the real-video validations are never trained on."""
    real_video_windows: str = flag(
        "",
        "validate on the real-video windows of this file (written by spk2img pack-data beside "
        "the packed sources: the same crops the clips give) instead of filming the held-out "
        "clips under --data",
    )
    data_mix: str = flag(
        "photos=0.5,clips=0.3,procedural=0.2",
        "shares of photo, clip and procedural samples (photos and clips need --data)",
    )
    speed_mix: str = flag(
        "",
        "shares of the scenes' motion classes: static, slow (0.03-0.3 px a spike frame), fast "
        "(0.5-3) and moderate (0.3-1), e.g. static=0,slow=0.7,moderate=0.2,fast=0.1; empty: "
        "static, slow and fast a third each",
    )
    sensor_preset: str = flag(
        "",
        "the real-like regime's sensor preset (JSON of spk2img fit-sensor); empty: the preset "
        "fitted to a real PKU capture that ships with spk2img",
    )
    ideal_share: float = flag(
        0.5,
        "share of the samples filmed by the noise-free sensor, the others by the real-like one "
        "(1: noise-free only, as simulated datasets such as spike-REDS are)",
    )
    display_share: float = flag(
        0.5,
        "share of the photo and clip samples whose 8-bit values are the light (v/255, the "
        "field's convention: spike-REDS, the real-video benchmark); the others undo the display "
        "gamma ((v/255)^2.2)",
    )
    workers: int = flag(1, "processes that make the batches ahead (0: the training process)")
    device: str = flag("cpu", "where to train", DEVICES)
    precision: str = flag(
        "auto",
        "the training steps' arithmetic: fp32; bf16, autocast to bfloat16 (convolutions in "
        "bf16, the loss and the weights in fp32), on a GPU and on a CPU with bf16 matrix units "
        "(Intel AMX: about twice as fast as fp32; on a CPU without them time both first); "
        "auto: bf16 on cuda, fp32 on cpu",
        PRECISIONS,
    )
    synthesis: str = flag(
        "auto",
        "who films the training windows: numpy, the reference simulator in the worker "
        "processes; torch, the same simulator batched on the training device (the workers only "
        "draw the scenes); auto: torch on cuda, numpy on cpu",
        SYNTHESES,
    )
    val_every: int = flag(500, "steps between validations")
    val_per_class: int = flag(
        2, "procedural validation scenes per motion x brightness class (9 classes)"
    )
    checkpoint_every: int = flag(
        100, "steps between checkpoints (last.pt); one is also written every 10 minutes"
    )
    threads: int = flag(1, "torch intra-op threads per process")
    log_every: int = flag(10, "steps between metrics lines")
    progress: bool = field(default=True, metadata={"help": "", "choices": None})
    """Show a progress bar on stderr (the ``--no-progress`` flag)."""
    ema_decay: float = flag(
        0.0,
        "keep an exponential moving average of the weights, this much of it kept each step "
        "(0.999: about the last 1,000 steps); validations score it and best.pt holds it; "
        "0: off",
    )
    align_weight: float = flag(
        0.0,
        "weight of the alignment term added to the loss: each pyramid level's aligning conv, "
        "sampling the neighbour's ground truth at its mean offset, should give the key's "
        '(docs/architecture.md, "Teaching the alignment"); 0: off, the paper\'s loss',
    )
    motion: str = flag(
        "",
        "the blocks' Lucas-Kanade motion over the member's own, as NAME=VALUE pairs: guided "
        "(1: it guides the alignment's offsets), read (1: the offset convs read it too, "
        "through convs that start at zero), levels, window, damping, "
        "damping_per_intensity, iterations, stride (where it is found, a multiple of the "
        "feature stride; e.g. guided=1,stride=4,window=15,damping=1e-4); --init takes any "
        "checkpoint of the member (with read=1 one without those convs grows into it); "
        "empty: the member's",
    )
    init: str = flag(
        "",
        "a checkpoint of the same member whose weights start the run (fine-tuning); the "
        "optimiser and schedule start afresh; not read when run-dir holds a last.pt to resume",
    )

    def films_on_device(self) -> bool:
        """Whether torch synthesis films the windows (``--synthesis``; auto: on cuda)."""
        return self.synthesis == "torch" or (self.synthesis == "auto" and self.device == "cuda")

    def autocasts_bf16(self) -> bool:
        """Whether the training steps autocast to bfloat16 (``--precision``; auto: on cuda)."""
        return self.precision == "bf16" or (self.precision == "auto" and self.device == "cuda")

    def __post_init__(self) -> None:
        if self.member not in MEMBERS:
            raise ValueError(f"unknown member {self.member!r}: choose one of {', '.join(MEMBERS)}")
        if self.device not in DEVICES:
            raise ValueError(f"--device {self.device}: choose one of {', '.join(DEVICES)}")
        if self.synthesis not in SYNTHESES:
            raise ValueError(f"--synthesis {self.synthesis}: choose one of {', '.join(SYNTHESES)}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"--precision {self.precision}: choose one of {', '.join(PRECISIONS)}")
        for name, least in AT_LEAST.items():
            if getattr(self, name) < least:
                raise ValueError(
                    f"--{name.replace('_', '-')} {getattr(self, name)}: must be >= {least}"
                )
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"--lr {self.lr}: must be a positive number")
        check_share("ideal_share", self.ideal_share)
        check_share("display_share", self.display_share)
        check_final_term(self.loss)
        if not (math.isfinite(self.align_weight) and self.align_weight >= 0):
            raise ValueError(f"--align-weight {self.align_weight}: must be a number >= 0")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"--ema-decay {self.ema_decay}: must be in [0, 1)")
        try:
            moved = with_motion(MEMBERS[self.member], self.motion)
        except ValueError as exc:
            raise ValueError(f"--motion {self.motion}: {exc}") from None
        if self.motion and not (moved.detail_aligned or moved.flow_guided):
            raise ValueError(
                f"--motion {self.motion}: {self.member} does not read the blocks' motion: "
                "add guided=1 (the motion guides its alignment)"
            )
