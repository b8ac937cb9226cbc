"""Score the shipped models and the classical methods on the real-video validation.

``python scripts/real_video_validation.py --data DATA [--models default,real,tiny,tiny-real]
[--seeds 2] [--json docs/real_video.json] [--md docs/real_video.md]`` films every clip of
:data:`spk2img.evaluation.real_video.REAL_VIDEO_CLIPS` found under ``DATA`` at each speed bin
(:mod:`spk2img.evaluation.real_video`), once per seed, and writes each method's PSNR/SSIM: over
all windows, per speed bin, per clip, with the spread over seeds (the standard deviation of the
overall mean between seeds) and over clips; the sections (``## ...``) written below the tables
in ``--md`` are kept. ``--add`` keeps the methods already in ``--json``
(scored on the same windows: the same clips and seeds) and scores only the models given. A
model is a shipped model's name or ``NAME=GRAPH.onnx``, an exported graph scored under NAME (a
candidate before it ships: ``--add`` to a copy of the JSON compares it with the shipped ones);
``--self-ensemble`` scores the models as their self-ensembles (four mirrored views averaged,
:mod:`spk2img.runtime.self_ensemble`).
Scoring a network takes minutes: on a terminal a bar per method counts its windows
(``--no-progress`` hides it).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from spk2img.cli.progress import add_progress_flags, progress_bar
from spk2img.evaluation.real_video import SPEEDS, real_video_scores, real_video_set
from spk2img.evaluation.scoring import (
    commands_made,
    dates_made,
    network_methods,
    tfi_window,
    tfp_best_window,
    tfp_window,
)

Method = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``(spikes, truth)`` of a window -> ``(H, W)`` image (spk2img.evaluation.scoring's shape)."""


def classical_methods() -> dict[str, Method]:
    return {
        "TFP-41": tfp_window,
        "TFP, best window (oracle)": tfp_best_window,
        "TFI": tfi_window,
    }


def markdown(results: dict) -> str:
    methods = results["methods"]
    lines = [
        "# Real-video validation",
        "",
        f"Made by `{results['command']}` on {results['date']}: {results['clips']} held-out real "
        f"clips ({results['windows']} windows: each clip at each speed bin, "
        f"{results['seeds']} seeds of the sensor's initial charge), noise-free, light = frame "
        "value / 255, whole frames less a 16-pixel margin (`spk2img.evaluation.real_video`). "
        "PSNR in dB; the seed spread is the standard deviation of the overall mean between "
        "seeds, the clip spread that of the per-clip means within a speed bin.",
        "",
        "| method | PSNR | SSIM | "
        + " | ".join(f"{b} PSNR (clip spread)" for b in SPEEDS)
        + " | seed spread |",
        "|---|---|---|" + "---|" * len(SPEEDS) + "---|",
    ]
    for name, r in methods.items():
        bins = " | ".join(
            f"{r['speed_bins'][b]['psnr']:.2f} ({r['speed_bins'][b]['clip_std_db']:.2f})"
            for b in SPEEDS
        )
        lines.append(
            f"| {name} | {r['psnr']:.2f} | {r['ssim']:.3f} | {bins} | {r['seed_std_db']:.3f} |"
        )
    speeds = results["speeds"]
    lines += [
        "",
        "Speed of each clip's window (median flow magnitude, px a spike frame), per bin:",
        "",
        "| clip | " + " | ".join(SPEEDS) + " | " + " | ".join(methods) + " (benchmark bin) |",
        "|---|" + "---|" * (len(SPEEDS) + len(methods)),
    ]
    for clip, by_bin in speeds.items():
        cells = [f"{by_bin[b]:.3f}" for b in SPEEDS]
        cells += [
            f"{m['speed_bins']['benchmark']['clips'][clip]['psnr']:.2f}" for m in methods.values()
        ]
        lines.append(f"| {clip} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", required=True)
    p.add_argument("--models", default="default,real,tiny,tiny-real")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=Path("docs/real_video.json"))
    p.add_argument("--md", type=Path, default=Path("docs/real_video.md"))
    p.add_argument("--add", action="store_true", help="add the models to --json's methods")
    p.add_argument(
        "--self-ensemble",
        action="store_true",
        help="score each model of --models as its self-ensemble (named 'NAME, self-ensemble')",
    )
    add_progress_flags(p)
    args = p.parse_args(argv)
    start = time.perf_counter()
    windows = real_video_set(args.data, seeds=args.seeds)
    if not windows:
        raise SystemExit(f"none of the real-video clips under {args.data}")
    print(f"{len(windows)} windows filmed in {time.perf_counter() - start:.0f} s", flush=True)
    earlier = json.loads(args.json.read_text()) if args.add else None
    if earlier and (earlier["windows"], earlier["seeds"]) != (len(windows), args.seeds):
        raise SystemExit(f"--add: {args.json} was scored on other windows or seeds")
    methods = {} if earlier else classical_methods()
    methods |= network_methods(args.models, args.threads, args.self_ensemble)
    results = dict(earlier["methods"]) if earlier else {}
    for name, method in methods.items():
        start = time.perf_counter()
        with progress_bar(args, len(windows), unit="window") as bar:
            bar.set_description(name)
            images = []
            for w in windows:
                images.append(method(w.spikes, w.truth))
                bar.update()
        results[name] = real_video_scores(windows, images)
        results[name]["seconds"] = time.perf_counter() - start
        print(f"{name}: {results[name]['psnr']:.2f} dB", flush=True)
    command = (
        "python scripts/real_video_validation.py --data DATA "
        f"--models {args.models} --seeds {args.seeds}"
        + (" --self-ensemble" if args.self_ensemble else "")
    )
    data = {
        "command": commands_made(earlier["command"], f"{command} --add") if earlier else command,
        "date": dates_made(earlier["date"] if earlier else None),
        "clips": len({w.clip for w in windows}),
        "windows": len(windows),
        "seeds": args.seeds,
        "speeds": {
            clip: {w.speed_bin: w.speed for w in windows if w.clip == clip}
            for clip in dict.fromkeys(w.clip for w in windows)
        },
        "methods": results,
    }
    args.json.write_text(json.dumps(data, indent=1) + "\n")
    args.md.write_text(markdown(data) + kept_notes(args.md))


def kept_notes(md: Path) -> str:
    """The written sections (``## ...`` onwards) of an existing ``md``, which the tables above
    them leave as they are; empty without any."""
    text = md.read_text() if md.is_file() else ""
    return text[text.index("\n## ") :] if "\n## " in text else ""


if __name__ == "__main__":
    main()
