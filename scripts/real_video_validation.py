"""Score the shipped models and the classical methods on the real-video validation.

``python scripts/real_video_validation.py --data DATA [--models default,real,tiny,tiny-real]
[--seeds 2] [--json docs/real_video.json] [--md docs/real_video.md]`` films every clip of
:data:`spk2img.evaluation.real_video.REAL_VIDEO_CLIPS` found under ``DATA`` at each speed bin
(:mod:`spk2img.evaluation.real_video`), once per seed, and writes each method's PSNR/SSIM: over
all windows, per speed bin, per clip, with the spread over seeds (the standard deviation of the
overall mean between seeds) and over clips.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from spk2img.evaluation.real_video import SPEEDS, RealVideoWindow, real_video_set
from spk2img.evaluation.scoring import group_scores, image_scores, mean_scores, tfp_best_window
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.loader import load_network
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES

Method = Callable[[RealVideoWindow], np.ndarray]


def classical_methods() -> dict[str, Method]:
    return {
        "TFP-41": lambda w: tfp(w.spikes, [CENTER_FRAME], FILM_FRAMES)[0],
        "TFP, best window (oracle)": lambda w: tfp_best_window(w.spikes, w.truth),
        "TFI": lambda w: tfi(w.spikes, [CENTER_FRAME])[0],
    }


def network_method(name: str, threads: int) -> Method:
    network = load_network(name, threads=threads, block_reuse=False)
    geometry = network.geometry
    return lambda w: network.predict(geometry.crop(w.spikes)[None].astype(np.float32))[0]


def summary(windows: list[RealVideoWindow], images: list[np.ndarray], seconds: float) -> dict:
    scores = image_scores(images, [w.truth for w in windows])
    seeds = sorted({w.seed for w in windows})
    per_seed = [
        mean_scores([s for s, w in zip(scores, windows, strict=True) if w.seed == seed])["psnr"]
        for seed in seeds
    ]
    clips = list(dict.fromkeys(w.clip for w in windows))
    per_bin = {}
    for speed_bin in SPEEDS:
        picked = [(s, w) for s, w in zip(scores, windows, strict=True) if w.speed_bin == speed_bin]
        if not picked:
            continue
        by_clip = group_scores([s for s, _ in picked], [w.clip for _, w in picked], clips)
        clip_psnr = [v["psnr"] for v in by_clip.values()]
        per_bin[speed_bin] = {
            **mean_scores([s for s, _ in picked]),
            "clip_std_db": float(np.std(clip_psnr)),
            "clips": by_clip,
        }
    return {
        **mean_scores(scores),
        "seed_psnr": per_seed,
        "seed_std_db": float(np.std(per_seed)),
        "speed_bins": per_bin,
        "seconds": seconds,
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", required=True)
    p.add_argument("--models", default="default,real,tiny,tiny-real")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=Path("docs/real_video.json"))
    p.add_argument("--md", type=Path, default=Path("docs/real_video.md"))
    args = p.parse_args()
    start = time.perf_counter()
    scenes, windows = real_video_set(args.data, seeds=args.seeds)
    if not windows:
        raise SystemExit(f"none of the real-video clips under {args.data}")
    print(f"{len(windows)} windows filmed in {time.perf_counter() - start:.0f} s", flush=True)
    methods = classical_methods()
    for name in filter(None, args.models.split(",")):
        methods[name] = network_method(name, args.threads)
    results = {}
    for name, method in methods.items():
        start = time.perf_counter()
        images = [method(w) for w in windows]
        results[name] = summary(windows, images, time.perf_counter() - start)
        print(f"{name}: {results[name]['psnr']:.2f} dB", flush=True)
    data = {
        "command": "python scripts/real_video_validation.py --data DATA "
        f"--models {args.models} --seeds {args.seeds}",
        "date": time.strftime("%Y-%m-%d"),
        "clips": len({s.clip for s in scenes}),
        "windows": len(windows),
        "seeds": args.seeds,
        "speeds": {
            clip: {s.speed_bin: s.speed for s in scenes if s.clip == clip}
            for clip in dict.fromkeys(s.clip for s in scenes)
        },
        "methods": results,
    }
    args.json.write_text(json.dumps(data, indent=1) + "\n")
    args.md.write_text(markdown(data))


if __name__ == "__main__":
    main()
