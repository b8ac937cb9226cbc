"""Real-data behaviour on the real spike-camera capture in ../shared/data/real (dim, static,
250x250, no ground truth): each shipped noise-free network's output is finite and in range, and
closer than TFP over the same 41 frames to a clean reference, TFP over all 199 frames (the
scene is a still photograph, so the long window is nearly noise-free)."""

from pathlib import Path

import numpy as np
import pytest

from spk2img.evaluation.metrics import psnr
from spk2img.runtime.classical import tfp
from spk2img.runtime.onnx_backend import OnnxModel, model_path

CAPTURE = Path(__file__).resolve().parents[2] / "shared/data/real/uhsr_helicopter_250x250.npz"

pytestmark = pytest.mark.skipif(not CAPTURE.is_file(), reason=f"real capture not at {CAPTURE}")


@pytest.fixture(scope="module")
def spikes():
    with np.load(CAPTURE) as z:
        return z["spk"]


@pytest.mark.parametrize("name", ["default", "cpu"])
def test_network_on_real_capture_is_finite_and_cleaner_than_tfp(spikes, name):
    reference = tfp(spikes, [100], 199)[0]
    model = OnnxModel(model_path(name), threads=1)
    for k in (40, 100, 160):
        window = spikes[k - 20 : k + 21][None].astype(np.float32)
        image = model(window)[0]
        assert image.shape == (250, 250)
        assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
        assert psnr(image, reference) > psnr(tfp(spikes, [k], 41)[0], reference)
        # plausibly exposed: the mean level agrees with the spike rate (I = rate / 0.6)
        assert abs(image.mean() - reference.mean()) < 0.25 * reference.mean()
