"""The alignment probe (spk2img.evaluation.alignment_probe): its pan moves content exactly, and
its slopes read 1 for sampling that follows the pan, 0 for sampling that ignores it, at every
pyramid level."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.evaluation.alignment_probe import (
    PROBE_SPEEDS,
    alignment_slopes,
    neighbour_offsets,
    pan_scene,
)
from spk2img.model import config as model_config
from spk2img.model.checkpoint import load_model
from spk2img.model.network import build_model
from spk2img.runtime.onnx_backend import model_path

SIZE = 128


def texture(seed: int = 0) -> np.ndarray:
    """A smooth random texture, ``(SIZE + 48, SIZE + 48)`` light in [0.1, 0.9]."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(size=(SIZE + 48, SIZE + 48))
    smooth = (noise + np.roll(noise, 1, 0) + np.roll(noise, 1, 1) + np.roll(noise, (1, 1))) / 4
    return (0.1 + 0.8 * (smooth - smooth.min()) / np.ptp(smooth)).astype(np.float32)


@settings(max_examples=10, deadline=None)
@given(st.integers(1, 3), st.integers(1, 12))
def test_the_pan_moves_the_content_straight_along_x_at_its_speed(speed, frames):
    scene = pan_scene(texture(), SIZE, SIZE, float(speed))
    before, after = scene.intensities([0.0, float(frames)])
    shift = speed * frames
    np.testing.assert_allclose(after[:, shift:], before[:, :-shift], atol=1e-5)


def with_motion(model, motion_of_speed):
    """``model`` whose blocks' motion is ``motion_of_speed(speed)``, for the probe's speeds in
    the order it films them."""
    speeds = iter(PROBE_SPEEDS)

    def block_motion(weighted):
        b, blocks, _, h, w = weighted.shape
        stride = model.config.feature_stride // model.config.sali_stride
        size = (b * (blocks - 1), 2, h // stride, w // stride)
        return motion_of_speed(next(speeds), size)

    model.block_motion = block_motion
    return model


def ideal_motion(model):
    frames = torch.tensor(neighbour_offsets(model), dtype=torch.float32)

    def motion(speed, size):
        flow = torch.zeros(size)
        flow[:, 1] = (speed * frames / model.config.feature_stride)[:, None, None]
        return flow

    return motion


def test_slopes_are_one_for_sampling_that_follows_the_pan_at_every_level():
    # a fresh flow-guided member predicts zero offsets: it samples exactly where its flow says
    model = with_motion(build_model("cpu"), ideal_motion(build_model("cpu")))
    slopes = alignment_slopes(model, texture(), SIZE, SIZE)
    for level in (1, 2, 3):
        assert slopes[f"align.dcn_pack.l{level}"] == pytest.approx(1.0, abs=1e-4)
    assert slopes["align.cas_dcn_pack"] == pytest.approx(0.0, abs=1e-6)  # no flow guides it


def test_slopes_are_zero_for_sampling_that_ignores_the_motion():
    model = with_motion(build_model("cpu"), lambda speed, size: torch.zeros(size))
    slopes = alignment_slopes(model, texture(), SIZE, SIZE)
    assert all(abs(s) < 1e-6 for s in slopes.values()), slopes


def test_half_the_motion_reads_half():
    model = build_model("cpu")
    ideal = ideal_motion(model)
    with_motion(model, lambda speed, size: ideal(speed, size) / 2)
    slopes = alignment_slopes(model, texture(), SIZE, SIZE)
    assert slopes["align.dcn_pack.l1"] == pytest.approx(0.5, abs=1e-4)


GUIDED = "guided=1,levels=2,window=15,damping=1e-4,damping_per_intensity=1e-3,iterations=4"
"""Motion settings (:func:`~spk2img.model.config.with_motion`) that guide a member's alignment."""


def test_a_full_size_member_guided_by_its_blocks_motion_follows_a_pan():
    """``flow_guided`` without a detail refinement: the shipped ``tiny``'s weights load as they
    are (the motion has none), and its deformable convs then sample along a pan by the blocks'
    Lucas-Kanade motion; found at 1/4 of the size (``motion_stride`` 4, then upsampled), where
    a neighbour block is a quarter as many pixels away and each pixel holds 16 pixels' spikes,
    it follows the pan much further than found at full size. Unguided, the shipped network
    does not follow it at all."""
    shipped = load_model(model_path("tiny").with_suffix(".pt"))
    slopes = {}
    guides = {"unguided": "", "full": GUIDED, "quarter": f"{GUIDED},stride=4"}
    for label, motion in guides.items():
        model = type(shipped)(model_config.with_motion(shipped.config, motion))
        model.load_state_dict(shipped.state_dict())  # strict: the same weights
        slopes[label] = alignment_slopes(model, texture(), SIZE, SIZE)
    for level in ("align.dcn_pack.l1", "align.dcn_pack.l2"):
        assert abs(slopes["unguided"][level]) < 0.01, slopes
        assert slopes["quarter"][level] > 0.3, slopes
        assert slopes["quarter"][level] > 2 * slopes["full"][level] > 0.05, slopes
