"""Binning on dim still scenes: the network with K frames merged against TFP, TFI and no binning.

``python scripts/binning_study.py --data DATA [--model default] [--rates
0.015,0.03,0.06] [--json OUT.json]`` films the first six held-out photographs of the natural
validation (:data:`~spk2img.evaluation.natural_validation.HELD_OUT_PHOTOS`; centre crops of
160x160, still, scaled to a mean firing rate) with the noise-free and the fitted sensor for
329 frames (41 x 8 + 1), reconstructs the middle frame with the shipped model at binning
1, 2, 3, 4, 6, 8 and with :func:`~spk2img.suggest_binning`'s choice, with TFP over 41 and over
205 frames and with TFI, and prints the mean PSNR per sensor and method as a markdown table.
PSNR is taken against the scene's own peak (``data_range = truth.max()``): a dim scene's
intensities stay far below 1.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from spk2img.evaluation.metrics import psnr
from spk2img.evaluation.natural_validation import find_held_out
from spk2img.io.light import SPIKE_RATE
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.runtime.binning import suggest_binning
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.onnx_backend import OnnxModel
from spk2img.runtime.stream import net_input
from spk2img.runtime.windows import net_window
from spk2img.sim.scenes import StillScene
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.simulator import SensorConfig, simulate
from spk2img.sim.sources import load_photo

BINNINGS = (1, 2, 3, 4, 6, 8)
SIDE = 160
FRAMES = net_window(PUBLISHED_GEOMETRY.window_frames, max(BINNINGS))


def dim_crop(photo: np.ndarray, rate: float) -> np.ndarray:
    """The centre ``SIDE x SIDE`` crop of a linear photo scaled to a mean of ``rate`` spikes a
    frame (intensity ``rate / 0.6``), clipped to [0, 1]."""
    h, w = photo.shape
    crop = photo[(h - SIDE) // 2 :, (w - SIDE) // 2 :][:SIDE, :SIDE]
    return np.clip(crop * (rate / SPIKE_RATE) / crop.mean(), 0.0, 1.0).astype(np.float32)


def network(model: OnnxModel, spikes: np.ndarray, center: int, binning: int) -> np.ndarray:
    window = net_input(
        spikes, center, net_window(PUBLISHED_GEOMETRY.window_frames, binning), binning
    )
    return model(window[None].astype(np.float32))[0] / binning


def study(photos: list[np.ndarray], model: OnnxModel, rate: float) -> dict[str, dict]:
    """``{sensor: {method: mean PSNR}}`` (and ``auto``: the mean binning chosen)."""
    sensors = {"ideal": SensorConfig.ideal(), "fitted": load_preset(FITTED_PRESET)}
    center = FRAMES // 2
    scores: dict[str, dict[str, list[float]]] = {name: {} for name in sensors}
    for i, photo in enumerate(photos):
        truth = dim_crop(photo, rate)
        for name, sensor in sensors.items():
            spikes = simulate(StillScene(truth), FRAMES, sensor, np.random.default_rng(i))
            auto = suggest_binning(spikes)
            images = {
                "TFP-41": tfp(spikes, [center], 41)[0],
                "TFP-205": tfp(spikes, [center], 205)[0],
                "TFI": tfi(spikes, [center], 41)[0],
                **{f"net K={k}": network(model, spikes, center, k) for k in BINNINGS},
                "net K=auto": network(model, spikes, center, auto),
            }
            row = scores[name]
            for method, image in images.items():
                row.setdefault(method, []).append(psnr(image, truth, float(truth.max())))
            row.setdefault("auto K", []).append(auto)
    return {s: {m: float(np.mean(v)) for m, v in row.items()} for s, row in scores.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="default")
    parser.add_argument("--rates", default="0.015,0.03,0.06")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    paths, _ = find_held_out([args.data])
    photos = [load_photo(p) for p in paths[:6]]
    model = OnnxModel(args.model, threads=1)
    results = {rate: study(photos, model, float(rate)) for rate in args.rates.split(",")}
    methods = list(next(iter(next(iter(results.values())).values())))
    print("| spikes/pixel/frame | sensor | " + " | ".join(methods) + " |")
    print("|---|---|" + "---|" * len(methods))
    for rate, by_sensor in results.items():
        for sensor, row in by_sensor.items():
            cells = [f"{row[m]:.1f}" if m == "auto K" else f"{row[m]:.2f}" for m in methods]
            print(f"| {rate} | {sensor} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
