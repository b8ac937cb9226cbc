"""``spk2img inspect FILE``: what a spike file holds before reconstructing it: frame count, the
likely frame sizes of a headerless ``.dat`` (with their coherence, spk2img.io.frame_size), the
firing rate and the binning ``--binning auto`` would take."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from spk2img.io.frame_size import size_scores
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, DatStream, read_spikes
from spk2img.runtime.binning import binning_for_rates, firing_rates

SHOWN_SIZES = 5
"""Candidate sizes printed for a ``.dat`` (and the given one, wherever it ranks)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect",
        help="frame count, likely frame sizes, firing rate and binning of a spike file",
        description=__doc__,
    )
    p.add_argument("input", type=Path, help=".dat (read as --height x --width) or .npy/.npz")
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height of a .dat")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width of a .dat")


def run(args: argparse.Namespace) -> int:
    spikes = read_spikes(args.input, args.height, args.width)
    frames, height, width = spikes.shape
    print(f"{args.input}: {frames} frames of {height}x{width}")
    if isinstance(spikes, DatStream):
        print("likely sizes (coherence in time + in space, of 2; a .dat stores no size):")
        scores = size_scores(args.input, args.height, args.width)
        given_size = [s for s in scores[SHOWN_SIZES:] if (s.height, s.width) == (height, width)]
        shown = scores[:SHOWN_SIZES] + given_size  # the given size, wherever it ranks
        for s in shown:
            given = "  <- as given" if (s.height, s.width) == (height, width) else ""
            print(
                f"  {s.height}x{s.width}: {s.score:.2f} (time {s.temporal:.2f}, space "
                f"{s.spatial:.2f}){given}"
            )
    rates = firing_rates(spikes)
    print(f"firing rate: {float(np.mean(rates)):.4f} spikes/pixel/frame")
    print(f"--binning auto would take {binning_for_rates(rates, frames)}")
    return 0
