"""How well the blocks' weights-free Lucas-Kanade motion finds a known motion, per setting.

``python scripts/motion_guide_study.py --data DATA [--clips 4] [--json docs/motion_guide.json]
[--md docs/motion_guide.md]`` pans the centre of each of the first ``--clips`` real-video
validation clips (:func:`spk2img.evaluation.alignment_probe.pan_scene`, 192x256) straight
along +x at 0, 0.14, 0.5 and 1.0 px a spike frame, filmed by the noise-free sensor, and, dimmed
to 15 % of its light, at 0 and 0.14 px a spike frame by the real-like sensor (the preset fitted
to a PKU capture). The shipped ``cpu`` network's SALI gives each block's intensity, exactly
what its :meth:`~spk2img.model.network.Spk2ImgNet.block_motion` reads; every motion setting
of :data:`SETTINGS` estimates each neighbour's motion to the key from it, and the table gives
the median end-point error against the pan's displacement (``speed * frames`` between the
blocks, at the motion's resolution, 4 px per pixel for ``cpu``), the border's two pixels left
out; the mean over clips and neighbours. A minute or two on two CPU cores.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from motion_study import PROBE_SIZE, probe_source  # scripts/, beside this one

from spk2img.evaluation.alignment_probe import neighbour_offsets, pan_scene
from spk2img.evaluation.real_video import find_real_video_clips
from spk2img.markdown import table_head, table_row
from spk2img.model.checkpoint import load_model
from spk2img.model.config import MEMBERS, MOTION_FIELDS
from spk2img.runtime.onnx_backend import model_path
from spk2img.sim.simulator import FILM_FRAMES, SensorConfig, simulate

CASES = (
    ("noise-free", 1.0, 0.0),
    ("noise-free", 1.0, 0.14),
    ("noise-free", 1.0, 0.5),
    ("noise-free", 1.0, 1.0),
    ("real-like, 15 % light", 0.15, 0.0),
    ("real-like, 15 % light", 0.15, 0.14),
)
"""(sensor, light gain, speed in px a spike frame) of each filmed pan."""
TWO_LEVELS = {
    "motion_levels": 2,
    "motion_window": 15,
    "motion_damping": 1e-6,
    "motion_damping_per_intensity": 1e-3,
    "motion_iterations": 4,
}
"""The settings the fine-tune ``cpu-lk2-v1`` trained with (training_state/README.md)."""
SETTINGS = {
    "cpu (one level, 5x5, damping 1e-3, 3 iterations)": {
        name: getattr(MEMBERS["cpu"], name) for name in MOTION_FIELDS
    },
    "two levels, 15x15, damping 1e-6 + 1e-3 x light, 4 iterations": TWO_LEVELS,
    "one level, 15x15, damping 1e-6 + 1e-3 x light, 4 iterations": TWO_LEVELS
    | {"motion_levels": 1},
    "two levels, 15x15, damping 1e-6 + 3e-3 x light, 4 iterations": TWO_LEVELS
    | {"motion_damping_per_intensity": 3e-3},
    "two levels, 15x15, damping 1e-5 + 1e-3 x light, 4 iterations": TWO_LEVELS
    | {"motion_damping": 1e-5},
    "two levels, 15x15, damping 1e-4 + 1e-3 x light, 4 iterations": TWO_LEVELS
    | {"motion_damping": 1e-4},
}
"""Label -> the config's motion fields (:data:`spk2img.model.config.MOTION_FIELDS`)."""


def block_estimates(model, spikes: np.ndarray) -> torch.Tensor:
    """The weighted SALI estimates ``(1, blocks, n * s * s, hp / s, wp / s)`` that ``model``'s
    :meth:`block_motion` reads on one window ``(F, H, W)`` 0/1."""
    seen = []

    def record(weighted):
        seen.append(weighted)
        return type(model).block_motion(model, weighted)

    model.block_motion = record
    try:
        with torch.no_grad():
            model(torch.from_numpy(spikes[None].astype(np.float32)))
    finally:
        del model.block_motion
    return seen[0]


def end_point_errors(model, estimates: torch.Tensor, speed: float) -> float:
    """Median end-point error (px at the motion's resolution) of ``model``'s block motion on
    ``estimates`` against a pan at ``speed``, the mean over the neighbours."""
    with torch.no_grad():
        flow = model.block_motion(estimates)[..., 2:-2, 2:-2]  # (neighbours, 2, h, w)
    frames = torch.tensor(neighbour_offsets(model) * speed / model.config.feature_stride)
    error = torch.sqrt((flow[:, 1] - frames.view(-1, 1, 1).float()) ** 2 + flow[:, 0] ** 2)
    return float(error.flatten(1).median(1).values.mean())


def markdown(results: dict) -> str:
    cases = [f"{sensor} @ {speed}" for sensor, _, speed in CASES]
    lines = [
        "# The blocks' Lucas-Kanade motion against a known pan",
        "",
        f"Made by `{results['command']}` on {results['date']}: median end-point error (px at the "
        "motion's resolution, 4 px per pixel for `cpu`) of each neighbour block's motion to the "
        f"key on pans of {results['clips']} real-video clips ({PROBE_SIZE[0]}x{PROBE_SIZE[1]}, "
        "straight along +x; speeds in px a spike frame), the mean over clips and neighbours; "
        "the block intensities are the shipped `cpu` network's. At 0.14 px/frame the neighbours "
        "are 0.25 and 0.49 px away at this resolution, at 1.0 px/frame 1.75 and 3.5 px; a "
        "motion of zero scores those.",
        "",
        *table_head(["setting", *cases]),
    ]
    for label, errors in results["errors"].items():
        lines.append(table_row([label, *(f"{e:.3f}" for e in errors)]))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", required=True)
    p.add_argument("--clips", type=int, default=4)
    p.add_argument("--json", type=Path, default=Path("docs/motion_guide.json"))
    p.add_argument("--md", type=Path, default=Path("docs/motion_guide.md"))
    args = p.parse_args(argv)
    clips = find_real_video_clips(args.data)[: args.clips]
    if not clips:
        raise SystemExit(f"none of the real-video clips under {args.data}")
    shipped = load_model(model_path("cpu").with_suffix(".pt"))
    networks = {}
    for label, fields in SETTINGS.items():
        networks[label] = type(shipped)(replace(shipped.config, **fields)).eval()
    errors: dict[str, list[list[float]]] = {label: [] for label in SETTINGS}
    for clip in clips:
        source = probe_source(clip)
        for case, (sensor, gain, speed) in enumerate(CASES):
            config = SensorConfig.ideal() if sensor == "noise-free" else SensorConfig.real()
            scene = pan_scene(source * gain, *PROBE_SIZE, speed)
            spikes = simulate(scene, FILM_FRAMES, config, np.random.default_rng([case, 20261203]))
            estimates = block_estimates(shipped, spikes)
            for label, network in networks.items():
                errors[label].append(end_point_errors(network, estimates, speed))
        print(f"{clip.name} done", flush=True)
    results = {
        "command": f"python scripts/motion_guide_study.py --data DATA --clips {args.clips}",
        "date": time.strftime("%Y-%m-%d"),
        "clips": len(clips),
        "cases": [list(c) for c in CASES],
        "settings": SETTINGS,
        "errors": {
            label: np.mean(np.reshape(e, (len(clips), len(CASES))), 0).round(4).tolist()
            for label, e in errors.items()
        },
    }
    args.json.write_text(json.dumps(results, indent=1) + "\n")
    args.md.write_text(markdown(results))
    print(f"wrote {args.json} and {args.md}")


if __name__ == "__main__":
    main()
