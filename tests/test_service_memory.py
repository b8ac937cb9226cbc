"""The service's memory estimate against the peak memory a model call really takes, for thin,
square and wide frames (issue: a 1x100000 frame was admitted at 1.4 GiB and peaked at 3.5)."""

import json
import subprocess
import sys

import pytest

from spk2img.model.config import get_config
from spk2img.service.reconstruction import NET_BYTES_PER_PIXEL, padded_pixels

SHAPES = [(1, 8000), (2, 4000), (8000, 1), (90, 90), (4, 2000), (40, 200)]
"""Thin (one and two rows or columns), square and wide frames of about 8,000 pixels."""

_MEASURE = """
import json, sys
import numpy as np
from spk2img.runtime.loader import load_network

def status_kib(field):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field + ":"))

height, width = int(sys.argv[1]), int(sys.argv[2])
network = load_network("default", threads=1, block_reuse=False, warm_up=False)
network.warm_up(8, 8)
window = np.zeros((1, network.geometry.window_frames, height, width), np.float32)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")  # the peak resident size starts again from the present one
before = status_kib("VmRSS")
network.predict(window)
print(json.dumps({"before": before * 1024, "peak": status_kib("VmHWM") * 1024}))
"""


def call_peak_bytes(height: int, width: int) -> int:
    """Bytes a model call of the shipped model at ``height x width`` adds to the process's
    peak resident memory (onnxruntime as the service runs it: arena off)."""
    out = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(height), str(width)],
        capture_output=True,
        text=True,
        check=True,
    )
    measured = json.loads(out.stdout.strip().splitlines()[-1])
    return measured["peak"] - measured["before"]


@pytest.mark.parametrize("shape", SHAPES, ids=[f"{h}x{w}" for h, w in SHAPES])
def test_every_frame_shape_peaks_inside_its_memory_estimate(shape):
    """The model call's peak (beyond the memory held before it) stays under the estimate per
    padded pixel; for one-row and one-column frames it is over an estimate per pixel, what
    let thin frames past the budget."""
    height, width = shape
    geometry = get_config("small").geometry
    estimate = padded_pixels(height, width, geometry) * NET_BYTES_PER_PIXEL
    peak = call_peak_bytes(height, width)
    assert peak <= estimate, (shape, peak / 2**20, estimate / 2**20)
    if min(shape) == 1:
        assert peak > height * width * NET_BYTES_PER_PIXEL, (shape, peak / 2**20)
