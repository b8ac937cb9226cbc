"""Where the shipped networks lose on real video: motion, and whether their alignment follows it.

``python scripts/motion_study.py --data DATA [--models default] [--probe default,cpu,tiny]
[--json docs/motion_study.json] [--md docs/motion_study.md]`` takes the truth of every clip of
the real-video validation's benchmark bin (:mod:`spk2img.evaluation.real_video`, seed 0, whole
frames) and films it three ways with the noise-free sensor: with the clip's own motion (the
validation's window), still, and panned straight at the window's measured speed
(:func:`spk2img.evaluation.alignment_probe.pan_scene`); each of ``--models`` is scored on all
three. Then each of ``--probe`` (shipped models' torch checkpoints) is probed for how far its
deformable convs' sampling follows a pan (:func:`~spk2img.evaluation.alignment_probe.
alignment_slopes`, on the centre of the first clip found). Minutes on two CPU cores.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from spk2img.evaluation.alignment_probe import PROBE_SPEEDS, alignment_slopes, pan_scene
from spk2img.evaluation.real_video import SPEEDS, film, find_real_video_clips, real_video_scenes
from spk2img.evaluation.scoring import image_scores, network_methods
from spk2img.markdown import table_head, table_row
from spk2img.model.checkpoint import load_model
from spk2img.runtime.onnx_backend import model_path
from spk2img.sim.scenes import StillScene
from spk2img.sim.simulator import CENTER_FRAME, FILM_FRAMES, SensorConfig, ground_truth, simulate
from spk2img.sim.sources import load_clip, to_light

VARIANTS = ("own motion", "still", "straight pan")
PROBE_SIZE = (192, 256)
"""Height and width of the probe's pan (its source has 40 px more on each side)."""


def filmed_variants(clip, speed_bin: str = "benchmark") -> tuple[float, dict]:
    """The window's speed (px a spike frame) and ``{variant: (spikes, truth)}`` for ``clip``."""
    (scene,) = real_video_scenes(clip.name, load_clip(clip), (speed_bin,), FILM_FRAMES)
    window = film(scene, 0)
    height, width = window.truth.shape
    still = simulate(StillScene(window.truth), FILM_FRAMES, SensorConfig.ideal(), rng(1))
    pan = pan_scene(window.truth, height, width, scene.speed)
    pan_truth = ground_truth(pan, [CENTER_FRAME])[0]
    panned = simulate(pan, FILM_FRAMES, SensorConfig.ideal(), rng(2))
    films = {
        "own motion": (window.spikes, window.truth),
        "still": (still, window.truth),
        "straight pan": (panned, pan_truth),
    }
    return scene.speed, films


def rng(seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, 20261203])


def probe_source(clip) -> np.ndarray:
    """The centre of ``clip``'s middle frame as light, :data:`PROBE_SIZE` plus 40 px a side."""
    frames = load_clip(clip)
    light = to_light(frames[len(frames) // 2], "display")
    h, w = (s + 80 for s in PROBE_SIZE)
    top, left = (light.shape[0] - h) // 2, (light.shape[1] - w) // 2
    if top < 0 or left < 0:
        raise SystemExit(f"{clip.name} is smaller than the probe's {h}x{w} source")
    return light[top : top + h, left : left + w]


def markdown(results: dict) -> str:
    models = results["models"]
    benchmark = SPEEDS["benchmark"]
    lines = [
        "# Motion study: where the networks lose on real video",
        "",
        f"Made by `{results['command']}` on {results['date']}: the truth of each clip of the "
        "real-video validation's benchmark bin (seed 0, whole frames), filmed with the clip's own "
        "motion, still, and panned straight at the window's speed; noise-free sensor. PSNR in dB.",
        "",
        *table_head(["clip", "speed (px/frame)", *(f"{m}: {v}" for m in models for v in VARIANTS)]),
    ]
    for row in results["clips"]:
        cells = [f"{row['psnr'][m][v]:.2f}" for m in models for v in VARIANTS]
        lines.append(table_row([row["clip"], f"{row['speed']:.3f}", *cells]))
    moving = [r for r in results["clips"] if np.isclose(r["speed"], benchmark)]
    for label, picked in (("mean", results["clips"]), (f"mean at {benchmark} px/frame", moving)):
        means = [np.mean([r["psnr"][m][v] for r in picked]) for m in models for v in VARIANTS]
        lines.append(
            table_row([f"{label} ({len(picked)} clips)", "", *(f"**{x:.2f}**" for x in means)])
        )
    convs = list(next(iter(results["probe"].values())))
    lines += [
        "",
        f"Alignment probe on `{results['probe_clip']}` ({PROBE_SIZE[0]}x{PROBE_SIZE[1]}, pans "
        f"along +x at {', '.join(str(s) for s in PROBE_SPEEDS[1:])} px/frame): the slope of each "
        "deformable conv's mean sampling shift on the displacement an aligning conv samples at "
        "(1: it follows the motion; 0: it samples the same places whatever the motion).",
        "",
        *table_head(["model", *(f"`{c}`" for c in convs)]),
    ]
    for model, slopes in results["probe"].items():
        lines.append(
            table_row([model, *(f"{slopes[c]:.3f}" if c in slopes else "—" for c in convs)])
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", required=True)
    p.add_argument("--models", default="default")
    p.add_argument("--probe", default="default,cpu,tiny")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=Path("docs/motion_study.json"))
    p.add_argument("--md", type=Path, default=Path("docs/motion_study.md"))
    args = p.parse_args(argv)
    clips = find_real_video_clips(args.data)
    if not clips:
        raise SystemExit(f"none of the real-video clips under {args.data}")
    methods = network_methods(args.models, args.threads)
    rows = []
    for clip in clips:
        start = time.perf_counter()
        speed, films = filmed_variants(clip)
        psnr = {
            name: {v: image_scores([m(*films[v])], [films[v][1]])[0][0] for v in VARIANTS}
            for name, m in methods.items()
        }
        rows.append({"clip": clip.name, "speed": speed, "psnr": psnr})
        print(f"{clip.name}: {psnr} ({time.perf_counter() - start:.0f} s)", flush=True)
    source = probe_source(clips[0])
    probe = {
        name: alignment_slopes(load_model(model_path(name).with_suffix(".pt")), source, *PROBE_SIZE)
        for name in filter(None, args.probe.split(","))
    }
    results = {
        "command": f"python scripts/motion_study.py --data DATA --models {args.models} "
        f"--probe {args.probe}",
        "date": time.strftime("%Y-%m-%d"),
        "models": list(methods),
        "clips": rows,
        "probe_clip": clips[0].name,
        "probe": probe,
    }
    args.json.write_text(json.dumps(results, indent=1) + "\n")
    kept = args.md.read_text().split("\n## ", 1)[1:] if args.md.exists() else []
    args.md.write_text(markdown(results) + "".join(f"\n## {k}" for k in kept))
    print(f"wrote {args.json} and {args.md}")


if __name__ == "__main__":
    main()
