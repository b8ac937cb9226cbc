"""Make docs/images/reconstructions.png: ground truth, TFP, TFI and the shipped network, side by
side, on the simulated fast-moving scene that examples/fast_motion_250x400.dat was made from
(``spk2img simulate … --motion fast --brightness normal --seed 10 --sensor real``).

Run: python scripts/readme_figure.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from spk2img.evaluation.metrics import psnr
from spk2img.io.light import to_display
from spk2img.runtime.classical import tfi, tfp
from spk2img.runtime.onnx_backend import OnnxModel, default_model_path
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, SpikeSimulator, ground_truth

SEED, CENTER = 10, 60
OUT = Path(__file__).resolve().parents[1] / "docs" / "images" / "reconstructions.png"


def main() -> None:
    rng = np.random.default_rng(SEED)
    scene = random_scene(rng, 250, 400, "fast", "normal")
    spikes = SpikeSimulator(scene, SensorConfig.real(), rng).run(CENTER + 21)
    truth = ground_truth(scene, [CENTER])[0]
    panels = [
        ("ground truth", truth),
        ("TFP (41 frames)", tfp(spikes, [CENTER], 41)[0]),
        ("TFI", tfi(spikes, [CENTER])[0]),
    ]
    if default_model_path().is_file():
        window = spikes[CENTER - 20 : CENTER + 21][None].astype(np.float32)
        panels.append(("Spk2ImgNet (shipped)", OnnxModel(threads=2)(window)[0]))
    tiles = []
    for name, image in panels:
        tile = Image.fromarray(to_display(image)).convert("RGB")
        label = name if image is truth else f"{name}: {psnr(image, truth):.1f} dB"
        draw = ImageDraw.Draw(tile)
        draw.rectangle((0, 0, 8 + 6 * len(label), 14), fill=(0, 0, 0))
        draw.text((4, 2), label, fill=(255, 255, 0))
        tiles.append(tile)
    grid = Image.new("RGB", (400 * 2 + 4, 250 * ((len(tiles) + 1) // 2) + 4 * (len(tiles) // 3)))
    for i, tile in enumerate(tiles):
        grid.paste(tile, ((i % 2) * 404, (i // 2) * 254))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    grid.save(OUT)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
