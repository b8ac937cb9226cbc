"""Spk2ImgNet: the grid_sample deformable conv against a loop reference, the published parameter
counts, shapes at odd sizes, finite outputs on extreme inputs, gradients everywhere."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.errors import InputError
from spk2img.model.block_split import key_terms, neighbour_terms
from spk2img.model.checkpoint import (
    CheckpointError,
    average_checkpoints,
    config_from_dict,
    config_to_dict,
    load_checkpoint,
    read_network,
    release_checkpoint,
    save_checkpoint,
)
from spk2img.model.complexity import count_macs, count_parameters, count_stream_macs
from spk2img.model.config import MEMBERS, PAPER, Spk2ImgNetConfig, get_config
from spk2img.model.deform_conv import ModulatedDeformConv2d, modulated_deform_conv2d
from spk2img.model.detail import MOTION_DEADBAND, DetailRefinement
from spk2img.model.motion import block_motion, coarse_to_fine, lucas_kanade
from spk2img.model.network import build_model, pad_to_multiple
from spk2img.model.sali import LightInference, fold, refold, unfold
from spk2img.model.warp import warp

torch.set_num_threads(1)


def naive_modulated_deform_conv2d(x, offset, mask, weight, bias, groups, padding=1, dilation=1):
    """torchvision's deform_conv2d (stride 1), one tap and one pixel at a time, in float64."""
    x, offset, mask, weight = (np.asarray(t, dtype=np.float64) for t in (x, offset, mask, weight))
    b, c_in, h, w = x.shape
    c_out, _, kh, kw = weight.shape
    h_out, w_out = offset.shape[-2:]
    per_group = c_in // groups

    def bilinear(image, y, x_):  # image (c, h, w); zero outside, as torchvision
        if y <= -1 or y >= h or x_ <= -1 or x_ >= w:
            return np.zeros(image.shape[0])
        y0, x0 = math.floor(y), math.floor(x_)
        value = np.zeros(image.shape[0])
        for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
            for xx, wx in ((x0, 1 - (x_ - x0)), (x0 + 1, x_ - x0)):
                if 0 <= yy < h and 0 <= xx < w:
                    value += wy * wx * image[:, yy, xx]
        return value

    columns = np.zeros((b, c_in, kh * kw, h_out, w_out))
    for n in range(b):
        for g in range(groups):
            channels = slice(g * per_group, (g + 1) * per_group)
            for i in range(kh):
                for j in range(kw):
                    k = i * kw + j
                    for y in range(h_out):
                        for x_ in range(w_out):
                            dy = offset[n, g * 2 * kh * kw + 2 * k, y, x_]
                            dx = offset[n, g * 2 * kh * kw + 2 * k + 1, y, x_]
                            sample = bilinear(
                                x[n, channels],
                                y - padding + i * dilation + dy,
                                x_ - padding + j * dilation + dx,
                            )
                            columns[n, channels, k, y, x_] = (
                                mask[n, g * kh * kw + k, y, x_] * sample
                            )
    out = np.einsum("ock,nckyx->noyx", weight.reshape(c_out, c_in, kh * kw), columns)
    if bias is not None:
        out += np.asarray(bias, dtype=np.float64)[None, :, None, None]
    return out


@pytest.mark.parametrize(
    ("groups", "c_in", "c_out", "kernel", "padding", "dilation"),
    [
        (1, 3, 2, 3, 1, 1),
        (2, 4, 3, 3, 1, 1),
        (4, 8, 5, 3, 1, 1),
        (2, 4, 2, 3, 2, 2),
        (3, 3, 2, 1, 0, 1),
    ],
)
def test_deform_conv_matches_loop_reference(groups, c_in, c_out, kernel, padding, dilation):
    gen = torch.Generator().manual_seed(groups * 100 + c_in)
    b, h, w = 2, 5, 7
    h_out, w_out = (
        h + 2 * padding - dilation * (kernel - 1),
        w + 2 * padding - dilation * (kernel - 1),
    )
    taps = kernel * kernel
    x = torch.randn(b, c_in, h, w, generator=gen, dtype=torch.float64)
    # offsets up to +-1.5 image sizes: many taps land far outside, some straddle the border
    offset = (
        (torch.rand(b, groups * 2 * taps, h_out, w_out, generator=gen, dtype=torch.float64) * 2 - 1)
        * 1.5
        * max(h, w)
    )
    offset[:, ::5] = offset[:, ::5].round()  # integer offsets: exact pixels and border lines
    mask = torch.rand(b, groups * taps, h_out, w_out, generator=gen, dtype=torch.float64)
    weight = torch.randn(c_out, c_in, kernel, kernel, generator=gen, dtype=torch.float64)
    bias = torch.randn(c_out, generator=gen, dtype=torch.float64)

    expected = naive_modulated_deform_conv2d(
        x, offset, mask, weight, bias, groups, padding, dilation
    )
    got = modulated_deform_conv2d(x, offset, mask, weight, bias, groups, padding, dilation)
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-9)
    got32 = modulated_deform_conv2d(
        *(t.float() for t in (x, offset, mask, weight, bias)), groups, padding, dilation
    )
    np.testing.assert_allclose(got32.numpy(), expected, rtol=1e-5, atol=1e-5)


def test_deform_conv_at_zero_offset_is_a_plain_conv():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4, 6, 9, generator=gen)
    weight = torch.randn(3, 4, 3, 3, generator=gen)
    mask = torch.rand(1, 2 * 9, 6, 9, generator=gen)
    offset = torch.zeros(1, 2 * 18, 6, 9)
    uniform = torch.full_like(mask, 0.25)
    torch.testing.assert_close(
        modulated_deform_conv2d(x, offset, uniform, weight, None, groups=2),
        0.25 * F.conv2d(x, weight, padding=1),
    )
    # the pack starts with zero offsets and mask 0.5
    pack = ModulatedDeformConv2d(4, 3, condition_channels=5, groups=2)
    condition = torch.randn(1, 5, 6, 9, generator=gen)
    torch.testing.assert_close(
        pack(x, condition), 0.5 * F.conv2d(x, pack.weight, padding=1) + pack.bias.view(1, 3, 1, 1)
    )


def test_paper_has_the_published_parameter_counts():
    model = build_model("paper")
    assert count_parameters(model) == 3_904_185
    assert count_parameters(model.sali) + count_parameters(model.features) == 1_117_200
    assert count_parameters(model.pyramid) + count_parameters(model.align) == 1_532_000
    assert count_parameters(model.fusion.masks) == 590_600
    assert count_parameters(model.fusion.reconstruct) == 664_385
    assert model.sali.spans == [(0, 13), (1, 12), (2, 11), (3, 10)]
    assert PAPER.window_frames == 41


def test_members_shrink_in_parameters_and_macs():
    params = {name: count_parameters(build_model(name)) for name in MEMBERS}
    assert 300_000 <= params["small"] <= 500_000
    assert 30_000 <= params["tiny"] <= 80_000
    macs = {name: count_macs(config, 40, 40) for name, config in MEMBERS.items()}
    assert macs["paper"] > macs["small"] > macs["tiny"] > 0
    # docs/cli.md (models): ~1.0 T MACs per 250x400 frame (252x400 once padded to a multiple of 4)
    assert count_macs(PAPER, 248, 400) == pytest.approx(1.0e12, rel=0.03)


def test_config_rejects_impossible_shapes():
    with pytest.raises(ValueError, match="deformable_groups"):
        Spk2ImgNetConfig(channels=12, deformable_groups=8)
    with pytest.raises(ValueError, match="sub-window"):
        Spk2ImgNetConfig(sali_subwindows=(13, 10))
    with pytest.raises(ValueError, match="unknown model"):
        get_config("huge")
    with pytest.raises(ValueError, match="sali_stride"):
        Spk2ImgNetConfig(sali_stride=2, feature_stride=3)
    with pytest.raises(ValueError, match="detail_depth"):
        Spk2ImgNetConfig(detail_hidden=8, detail_depth=0)
    with pytest.raises(ValueError, match="detail_aligned"):
        Spk2ImgNetConfig(detail_aligned=True)
    Spk2ImgNetConfig(flow_guided=True)  # the motion guides the alignment, no refinement needed
    with pytest.raises(ValueError, match="motion_levels"):
        Spk2ImgNetConfig(pyramid_levels=2, motion_levels=3)
    with pytest.raises(ValueError, match="motion_window must be odd"):
        Spk2ImgNetConfig(motion_window=4)
    with pytest.raises(ValueError, match="damping"):
        Spk2ImgNetConfig(motion_damping=0.0)


@settings(max_examples=25, deadline=None)
@given(
    stride=st.sampled_from([1, 2]),
    old=st.tuples(st.integers(1, 6), st.integers(1, 3)),
    extra=st.tuples(st.integers(0, 5), st.integers(0, 2)),
    seed=st.integers(0, 2**16),
)
def test_a_grown_detail_refinement_computes_what_the_smaller_one_did(stride, old, extra, seed):
    """Widened and deepened from trained (random, non-zero) weights, the refinement's output is
    unchanged; a refinement does not take the weights of a wider one."""
    torch.manual_seed(seed)
    (hidden, depth), estimates = old, 3 * stride**2
    small = DetailRefinement(estimates, hidden, stride, depth)
    small.body[-1].reset_parameters()  # a trained refinement's output conv is not zero
    big = DetailRefinement(estimates, hidden + extra[0], stride, depth + extra[1])
    big.grow_from(small.state_dict())
    pred = torch.rand(2, 1, 4 * stride, 6 * stride)
    est = torch.rand(2, 1, estimates, 4, 6)
    with torch.no_grad():
        torch.testing.assert_close(big(pred, est), small(pred, est))
    with pytest.raises(ValueError, match="wider or deeper"):
        small.grow_from(DetailRefinement(estimates, hidden + 1, stride, depth).state_dict())
    three = DetailRefinement(3 * estimates, hidden, stride, depth)
    three.body[-1].reset_parameters()
    aligned = DetailRefinement(3 * estimates, hidden, stride, depth, motion_stride=2 * stride)
    aligned.grow_from(three.state_dict())  # on a still scene: the same output
    still = torch.rand(2, 1, estimates, 4, 6).expand(2, 3, estimates, 4, 6)
    motion = block_motion(still, stride, 2 * stride)
    with torch.no_grad():
        torch.testing.assert_close(aligned(pred, still, motion), three(pred, still))


@settings(max_examples=30, deadline=None)
@given(
    dy=st.integers(-3, 3),
    dx=st.integers(-3, 3),
    fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_warp_samples_where_the_flow_points(dy, dx, fraction, seed):
    """A whole-pixel flow moves the image by whole pixels (the border repeated outside it); a
    fractional one along x interpolates the two pixels it falls between."""
    image = torch.rand(1, 2, 7, 9, generator=torch.Generator().manual_seed(seed))
    flow = torch.tensor([float(dy), float(dx)]).view(1, 2, 1, 1).expand(1, 2, 7, 9)
    rows = (torch.arange(7) + dy).clamp(0, 6)
    cols = (torch.arange(9) + dx).clamp(0, 8)
    torch.testing.assert_close(warp(image, flow), image[:, :, rows][:, :, :, cols])
    half = torch.tensor([0.0, fraction]).view(1, 2, 1, 1).expand(1, 2, 7, 9)
    mixed = (1 - fraction) * image[..., :-1] + fraction * image[..., 1:]
    torch.testing.assert_close(warp(image, half)[..., :-1], mixed)


def smooth_scene(
    shape: tuple[int, ...], dy: float, dx: float, seed: int, period: float = 16.0
) -> torch.Tensor:
    """Four sinusoids (one in each 45-degree sector, periods of ``period`` to twice that, px)
    moved by ``(dy, dx)`` pixels: ``scene(y - dy, x - dx)``, ``shape`` ``(..., h, w)``, about
    0.1 .. 0.5."""
    generator = torch.Generator().manual_seed(seed)
    y = torch.arange(shape[-2], dtype=torch.float64).view(-1, 1) - dy
    x = torch.arange(shape[-1], dtype=torch.float64).view(1, -1) - dx
    scene = torch.full(shape[-2:], 0.3, dtype=torch.float64)
    for sector in range(4):
        angle, length, phase = torch.rand(3, generator=generator, dtype=torch.float64)
        angle, length = (sector + angle) * math.pi / 4, period * (1 + length)
        along = y * math.sin(angle) + x * math.cos(angle)
        scene = scene + 0.05 * torch.cos(2 * math.pi * along / length + 2 * math.pi * phase)
    return scene.float().expand(shape)


def test_sampling_positions_stay_float32_under_bf16_autocast():
    """bf16 keeps 8 significant bits: a position of 60.3 px in it is 60.25, and 300.3 is 300.
    Under bf16 autocast (training, GPU inference) the deformable conv and the warp still sample
    where an fp32 run does: 0.3 px into a 64x320 wave of amplitude 1 their outputs stay within
    what bf16 values cost (0.004; with positions in bf16 the deform conv was 0.73 off here)."""
    h, w = 64, 320
    rows, cols = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    x = torch.sin(cols / 3.0 + rows / 5.0).expand(1, 4, h, w).contiguous()
    offset, mask = torch.full((1, 2 * 9, h, w), 0.3), torch.ones(1, 9, h, w)
    weight = torch.eye(4).view(4, 4, 1, 1).repeat(1, 1, 3, 3) / 9  # the mean of the nine taps
    flow = torch.full((1, 2, h, w), 0.3)
    reference = modulated_deform_conv2d(x, offset, mask, weight, None, 1), warp(x, flow)
    with torch.autocast("cpu", torch.bfloat16):
        args = x.bfloat16(), offset.bfloat16(), mask.bfloat16()
        autocast = modulated_deform_conv2d(*args, weight, None, 1), warp(x.bfloat16(), flow)
    for ours, fp32 in zip(autocast, reference, strict=True):
        assert (ours.float() - fp32).abs().max() < 0.01


@settings(max_examples=25, deadline=None)
@given(dy=st.floats(-1.5, 1.5), dx=st.floats(-1.5, 1.5), seed=st.integers(0, 2**16))
def test_lucas_kanade_finds_the_motion_of_a_textured_scene(dy, dx, seed):
    """A textured scene moved by up to 1.5 px (sub-pixel) is carried back onto itself: the
    flow's median is the motion to 0.2 px away from the border (bilinear sampling and the
    aperture problem bias it locally); identical images give no flow."""
    key = smooth_scene((1, 1, 40, 48), 0.0, 0.0, seed)
    moved = smooth_scene((1, 1, 40, 48), dy, dx, seed)
    flow = lucas_kanade(key, moved, window=7, damping=1e-6, iterations=5)[..., 8:-8, 8:-8]
    assert abs(flow[:, 0].median() - dy) < 0.2 and abs(flow[:, 1].median() - dx) < 0.2
    assert lucas_kanade(key, key).abs().max() < 1e-5


@settings(max_examples=15, deadline=None)
@given(dx=st.floats(3.0, 5.0), seed=st.integers(0, 2**16))
def test_coarse_to_fine_follows_motion_beyond_one_level(dx, seed):
    """A shift of 3-5 px on a 24-48 px texture: one Gauss-Newton step at one level falls short
    (the linearisation holds for a fraction of the period), one step at each of two levels
    comes at least twice as close (the median, away from the border); identical images give
    no flow at any number of levels."""
    key = smooth_scene((1, 1, 48, 64), 0.0, 0.0, seed, period=24.0)
    moved = smooth_scene((1, 1, 48, 64), 0.0, dx, seed, period=24.0)
    settings_ = {"window": 7, "damping": 1e-6, "iterations": 1}
    two = coarse_to_fine(key, moved, 2, **settings_)[..., 10:-10, 10:-10].median(-1).values
    one = coarse_to_fine(key, moved, 1, **settings_)[..., 10:-10, 10:-10].median(-1).values
    two_error, one_error = abs(two[:, 1].median() - dx), abs(one[:, 1].median() - dx)
    assert two_error < 0.2 and two_error < one_error / 2 and abs(two[:, 0].median()) < 0.5
    assert coarse_to_fine(key, key, 3, **settings_).abs().max() < 1e-5


def test_damping_per_intensity_is_the_neighbourhoods_mean_light_times_it():
    """Where ``(key + other) / 2`` is ``m`` everywhere, ``damping_per_intensity=b`` gives the
    flow of a constant damping ``b * m``; it damps more than its floor alone; a black pair
    (no gradient, no light) gives zero flow, not a division by zero."""
    texture = smooth_scene((1, 1, 40, 48), 0.0, 0.0, 3) - 0.3
    key, other = 0.2 + texture, 0.2 - texture  # mean 0.2 at every pixel
    per_intensity = lucas_kanade(key, other, 5, 1e-6, 3, damping_per_intensity=1e-2)
    constant = lucas_kanade(key, other, 5, 1e-6 + 0.2 * 1e-2, 3)
    torch.testing.assert_close(per_intensity, constant, rtol=1e-4, atol=1e-5)
    moved = smooth_scene((1, 1, 40, 48), 0.0, 1.0, 3)
    key = smooth_scene((1, 1, 40, 48), 0.0, 0.0, 3)
    floor_only = lucas_kanade(key, moved, 5, 1e-6, 3)[..., 8:-8, 8:-8]
    damped = lucas_kanade(key, moved, 5, 1e-6, 3, damping_per_intensity=1e-2)[..., 8:-8, 8:-8]
    assert damped[:, 1].median() < floor_only[:, 1].median() - 0.1
    black = torch.zeros(1, 1, 16, 16)
    assert torch.equal(
        lucas_kanade(black, black, 5, 1e-6, 3, damping_per_intensity=1e-3),
        torch.zeros(1, 2, 16, 16),
    )


def test_block_motion_is_float32_under_bf16_autocast():
    """The blocks' motion is computed in float32 whether or not the training autocasts to
    bf16: the same flow to float rounding."""
    estimates = smooth_scene((2, 3, 4, 32, 32), 0.0, 0.0, 5) + 0.1 * torch.rand(2, 3, 4, 32, 32)
    settings_ = {"levels": 2, "window": 9, "damping": 1e-6, "damping_per_intensity": 1e-3}
    reference = block_motion(estimates, 1, 2, **settings_)
    with torch.autocast("cpu", torch.bfloat16):
        autocast = block_motion(estimates, 1, 2, **settings_)
    assert autocast.dtype == torch.float32
    torch.testing.assert_close(autocast, reference)


@settings(max_examples=20, deadline=None)
@given(dy=st.integers(-2, 2), dx=st.integers(-2, 2), seed=st.integers(0, 2**16))
def test_a_flow_moves_every_tap_of_the_deformable_conv(dy, dx, seed):
    """A whole-pixel flow given to a deformable conv samples the input that far away: its
    output is the flow-free output moved by the flow (inside the image)."""
    torch.manual_seed(seed)
    dcn = ModulatedDeformConv2d(4, 3, 2, groups=2)
    x, condition = torch.randn(1, 4, 10, 12), torch.randn(1, 2, 10, 12)
    with torch.no_grad():
        dcn.conv_offset_mask.weight.normal_(0.0, 0.01)  # small offsets, masks of every kind
        flow = torch.tensor([float(dy), float(dx)]).view(1, 2, 1, 1).expand(1, 2, 10, 12)
        moved_condition = torch.roll(condition, (-dy, -dx), dims=(2, 3))  # read at p + flow
        moved = dcn(x, moved_condition, flow)[..., 3:-3, 3:-3]
        plain = dcn(x, condition)[..., 3 + dy : 10 - 3 + dy, 3 + dx : 12 - 3 + dx]
    torch.testing.assert_close(moved, plain)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(
    stride=st.sampled_from([1, 2]),
    shift=st.tuples(st.sampled_from([-1, 0, 1]), st.sampled_from([-1, 0, 1])),
    seed=st.integers(0, 2**16),
)
def test_the_aligned_refinement_warps_each_neighbour_onto_the_key(stride, shift, seed):
    """Blocks ``t`` blocks from the key that see a textured scene moved by ``t * shift`` px
    come out of :meth:`DetailRefinement.align`, given their
    :func:`~spk2img.model.motion.block_motion`, moved back by their motion less the dead band
    (to 4 % of the scene, away from the border); the two outer ones start further off (by 1.2
    times the aligned error at least: over 1,200 scenes the least ratio was 1.28, the median
    3.8); the key's own estimates are untouched. Derandomized: the same examples every run."""
    n, height, width, margin = 2, 48, 64, 12
    refinement = DetailRefinement(5 * n * stride**2, 4, stride, 1, motion_stride=4)

    def view(dy: float, dx: float) -> torch.Tensor:  # strong, coarse texture (motion at 1/4)
        return 3 * smooth_scene((1, n, height, width), dy, dx, seed, period=40.0)

    def left(motion: int) -> float:  # the motion the dead band leaves, px
        carried = -motion - max(-MOTION_DEADBAND, min(MOTION_DEADBAND, -motion))
        return motion + carried

    views = [view(t * shift[0], t * shift[1]) for t in range(-2, 3)]
    estimates = torch.stack([fold(v, stride) for v in views], dim=1)
    with torch.no_grad():
        aligned = refinement.align(estimates, block_motion(estimates, stride, 4))
    assert aligned.shape == estimates.shape
    assert torch.equal(aligned[:, 2], estimates[:, 2])
    inside = (..., slice(margin, -margin), slice(margin, -margin))
    for t, block in ((-2, 0), (-1, 1), (1, 3), (2, 4)):
        expected = view(left(t * shift[0]), left(t * shift[1]))[inside]
        moved = unfold(aligned[:, block], stride)[inside]
        error = (moved - expected).abs().max()
        assert error < 0.04 * expected.max()
        if shift != (0, 0) and abs(t) == 2:  # read unaligned: further off
            assert (views[block][inside] - expected).abs().max() > 1.2 * error


@settings(max_examples=30, deadline=None)
@given(
    stride=st.integers(1, 4),
    channels=st.integers(1, 3),
    rows=st.integers(1, 3),
    cols=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
@pytest.mark.parametrize("exporting", [False, True], ids=["eager", "onnx-export"])
def test_fold_puts_each_patch_pixel_in_its_documented_channel(
    exporting, stride, channels, rows, cols, seed
):
    """Both ways of folding (the eager pixel unshuffle, and the one-hot grouped conv the ONNX
    export writes) put each pixel exactly in its channel."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.randn(2, channels, rows * stride, cols * stride, generator=generator)
    with mock.patch("torch.onnx.is_in_onnx_export", return_value=exporting):
        folded = fold(x, stride)
    assert folded.shape == (2, channels * stride**2, rows, cols)
    for c in range(channels):
        for y in range(rows * stride):
            for x_ in range(cols * stride):
                channel = c * stride**2 + (y % stride) * stride + x_ % stride
                assert torch.equal(folded[:, channel, y // stride, x_ // stride], x[:, c, y, x_])
    assert torch.equal(unfold(folded, stride), x)


@settings(max_examples=20, deadline=None)
@given(
    stride=st.integers(1, 2),
    step=st.integers(1, 3),
    channels=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
@pytest.mark.parametrize("exporting", [False, True], ids=["eager", "onnx-export"])
def test_refold_is_an_unfold_then_a_fold(exporting, stride, step, channels, seed):
    """Both ways of refolding (the eager pair, and the one-hot grouped conv the ONNX export
    writes) give exactly the image folded at the new stride."""
    generator = torch.Generator().manual_seed(seed)
    image = torch.randn(2, channels, 6 * stride * step, 4 * stride * step, generator=generator)
    with mock.patch("torch.onnx.is_in_onnx_export", return_value=exporting):
        refolded = refold(fold(image, stride), stride, stride * step)
    assert torch.equal(refolded, F.pixel_unshuffle(image, stride * step))


def _averaging_sali(stride: int) -> LightInference:
    """A folded SALI whose every estimate is the mean spike count of its sub-window at each
    pixel (hidden = stride**2: one hidden channel per pixel of the patch) and whose attention
    weighs every estimate by sigmoid(0) = 1/2."""
    pixels = stride**2
    sali = LightInference(13, (13, 11, 9, 7), pixels, 4, stride)
    with torch.no_grad():
        for parameter in sali.parameters():
            parameter.zero_()
        for branch, n in zip(sali.branches, (13, 11, 9, 7), strict=True):
            for p in range(pixels):
                branch[0].weight[p, p::pixels, 1, 1] = 1 / n  # mean over the sub-window's frames
                branch[2].weight[p, p, 1, 1] = 1
    return sali


def test_folded_sali_estimates_stay_at_their_pixels():
    """With SALI on folded 4x4 patches, the estimates of each sub-window, unfolded, sit at the
    pixels whose spikes made them: an averaging SALI gives each sub-window's spike mean."""
    stride, h, w = 4, 8, 12
    block = (torch.rand(3, 13, h, w, generator=torch.Generator().manual_seed(2)) < 0.4).float()
    weighted, estimates = _averaging_sali(stride)(fold(block, stride))
    spans = [(0, 13), (1, 12), (2, 11), (3, 10)]
    expected = torch.stack([block[:, a:b].mean(1) for a, b in spans], dim=1)  # (3, 4, h, w)
    torch.testing.assert_close(unfold(estimates, stride), expected)
    torch.testing.assert_close(unfold(weighted, stride), expected / 2)


def test_the_cpu_member_reads_each_block_of_the_window_folded():
    """``cpu`` slices its five blocks out of the folded window (2x2 patches) and refolds
    SALI's output at its feature stride (4x4): its estimates (averaging weights) are each
    block's sub-window means at every pixel of an odd-sized window, and its features see the
    averages where a stride-1 SALI would put them."""
    model = build_model("cpu").eval()
    cfg = model.config
    model.sali = _averaging_sali(cfg.sali_stride)
    seen = []  # the feature extractor's input
    model.features.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    spikes = (torch.rand(1, 41, 21, 35, generator=torch.Generator().manual_seed(3)) < 0.3).float()
    with torch.no_grad():
        _, estimates = model(spikes)  # (1, 5, 4, 21, 35), divided by 0.6
    padded = pad_to_multiple(spikes, cfg.size_multiple)[0]  # (41, 32, 48)
    spans = [(0, 13), (1, 12), (2, 11), (3, 10)]
    for block, start in enumerate((0, 7, 14, 21, 28)):
        means = torch.stack([padded[start + a : start + b].mean(0) for a, b in spans])
        torch.testing.assert_close(estimates[0, block] * 0.6, means[:, :21, :35])
        weighted = fold(means[None] / 2, cfg.feature_stride)[0]  # as from a stride-1 SALI
        torch.testing.assert_close(seen[0][block], weighted)


@given(h=st.integers(1, 40), w=st.integers(1, 40), multiple=st.sampled_from([1, 2, 4, 8, 16]))
def test_padding_reaches_the_next_multiple_by_replicating_the_last_row_and_column(h, w, multiple):
    x = torch.arange(h * w, dtype=torch.float32).view(1, 1, h, w)
    padded = pad_to_multiple(x, multiple)
    hp, wp = padded.shape[-2:]
    assert hp % multiple == wp % multiple == 0 and h <= hp < h + multiple and w <= wp < w + multiple
    assert torch.equal(padded[..., :h, :w], x)
    assert torch.equal(padded[..., h:, :w], x[..., -1:, :].expand(-1, -1, hp - h, -1))
    assert torch.equal(padded[..., :, w:], padded[..., :, w - 1 : w].expand(-1, -1, -1, wp - w))


def test_paper_forward_on_a_small_window():
    model = build_model("paper").eval()
    spikes = (torch.rand(1, 41, 24, 36, generator=torch.Generator().manual_seed(1)) < 0.3).float()
    with torch.no_grad():
        image, estimates = model(spikes)
    assert image.shape == (1, 1, 24, 36)
    assert estimates.shape == (1, 5, 4, 24, 36)
    assert torch.isfinite(image).all() and image.min() >= 0 and image.max() <= 1


def _extreme_inputs(height: int, width: int) -> dict[str, torch.Tensor]:
    single = torch.zeros(1, 41, height, width)
    single[0, 20, height // 2, width // 3] = 1
    return {
        "zeros": torch.zeros(1, 41, height, width),
        "ones": torch.ones(1, 41, height, width),
        "single spike": single,
    }


@pytest.mark.parametrize("member", list(MEMBERS))
@pytest.mark.parametrize("training", [False, True], ids=["eval", "train"])
def test_odd_sizes_and_extreme_inputs_give_finite_outputs(member, training):
    torch.manual_seed(0)
    model = build_model(member).train(training)
    for name, spikes in _extreme_inputs(17, 23).items():
        with torch.no_grad():
            image, estimates = model(spikes)
        assert image.shape == (1, 1, 17, 23), name
        assert estimates.shape == (1, 5, 4, 17, 23), name
        assert torch.isfinite(image).all() and torch.isfinite(estimates).all(), name
        if not training:
            assert image.min() >= 0 and image.max() <= 1, name


@pytest.mark.parametrize("member", ["paper", "tiny"])
def test_gradients_reach_every_parameter(member):
    torch.manual_seed(0)
    model = build_model(member).train()
    # offset/mask predictors start at zero (as in EDVR), which blocks the gradient to the offset
    # features until the first update; give them a trained-looking state first
    for module in model.modules():
        if isinstance(module, ModulatedDeformConv2d):
            torch.nn.init.normal_(module.conv_offset_mask.weight, std=0.01)
    spikes = (torch.rand(2, 41, 12, 20) < 0.4).float()
    image, estimates = model(spikes)
    (image.abs().mean() + estimates.abs().mean()).backward()
    silent = [
        n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0
    ]
    assert not silent


@pytest.mark.parametrize("member", ["small", "tiny"])
def test_offset_conv_terms_add_up_to_the_conv_on_the_pair(member):
    """The first offset conv of each level is computed as a neighbour term plus a key term;
    together they are the conv on ``[neighbour, key]``."""
    torch.manual_seed(0)
    model = build_model(member).eval()
    c, levels = model.config.channels, model.config.pyramid_levels
    neighbour = [torch.randn(2, c, 16 // 2**i, 24 // 2**i) for i in range(levels)]
    key = [torch.randn(2, c, 16 // 2**i, 24 // 2**i) for i in range(levels)]
    terms = zip(neighbour_terms(model.align, neighbour), key_terms(model.align, key), strict=True)
    for i, (n_term, k_term) in enumerate(terms, start=1):
        conv = model.align.offset_conv1[f"l{i}"]
        whole = conv(torch.cat([neighbour[i - 1], key[i - 1]], dim=1))
        torch.testing.assert_close(n_term + k_term, whole, atol=1e-5, rtol=1e-5)


def test_stream_macs_split_the_network():
    """Encoding five blocks and running the head costs what the one-shot forward costs, up to
    the offset-conv terms the encoder computes for both roles of every block."""
    for config in MEMBERS.values():
        encoder, head = count_stream_macs(config, 40, 48)
        whole = count_macs(config, 40, 48)
        assert 0 < head < whole < 5 * encoder + head
        assert (5 * encoder + head - whole) / whole < 0.05


def test_stored_configs_load_with_retired_fields_only_where_they_change_nothing():
    """Checkpoints of the intensity-base era store ``intensity_base``: false loads as today's
    network, true (a network no longer built) and unknown fields are refused by name."""
    stored = config_to_dict(get_config("lite"))
    assert config_from_dict(stored) == get_config("lite")
    assert config_from_dict(stored | {"intensity_base": False}) == get_config("lite")
    with pytest.raises(ValueError, match="intensity_base"):
        config_from_dict(stored | {"intensity_base": True})
    with pytest.raises(ValueError, match="does not know.*'wings'"):
        config_from_dict(stored | {"wings": 2})


def test_checkpoint_reader_round_trips_and_refuses_what_is_not_a_checkpoint(tmp_path):
    """One loader serves export, ``--init`` and resume: it returns the stored network with its
    weights, and anything else (missing, corrupt, not a dict, no or a broken config, weights of
    another shape) is a :class:`CheckpointError` naming the file, never a torch traceback."""
    torch.manual_seed(0)
    config = get_config("tiny")
    model = build_model(config)
    good = tmp_path / "good.pt"
    save_checkpoint(good, model=model.state_dict(), config=config_to_dict(config), step=5)
    loaded, state = read_network(good)
    assert state["step"] == 5 and not loaded.training
    for name, tensor in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor)

    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint")
    torch.save([1, 2, 3], tmp_path / "list.pt")
    save_checkpoint(tmp_path / "no_config.pt", model=model.state_dict())
    broken = config_to_dict(config) | {"channels": 13}  # not divisible by the groups
    save_checkpoint(tmp_path / "bad_config.pt", model=model.state_dict(), config=broken)
    other = config_to_dict(get_config("lite"))
    save_checkpoint(tmp_path / "other_shape.pt", model=model.state_dict(), config=other)
    cases = {
        "missing.pt": "no such checkpoint",
        "garbage.pt": "not a spk2img training checkpoint",
        "list.pt": "no state dict",
        "no_config.pt": "KeyError",
        "bad_config.pt": "deformable_groups",
        "other_shape.pt": "RuntimeError",
    }
    for name, reason in cases.items():
        with pytest.raises(CheckpointError, match=reason) as caught:
            read_network(tmp_path / name)
        assert name in str(caught.value)


def test_average_checkpoints_script_reads_fractions_and_refuses_bad_input_in_one_line(tmp_path):
    """scripts/average_checkpoints.py: ``--weights 2/3,1/3`` is a weighted mean, and
    ``--chosen-on`` is recorded as its ``val_set``; a missing file exits 2 with one line, as the
    spk2img CLI does (the weights' checks: the test below)."""
    config = get_config("tiny")
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        paths.append(tmp_path / f"seed{seed}.pt")
        save_checkpoint(
            paths[-1], model=build_model(config).state_dict(), config=config_to_dict(config)
        )
    script = [sys.executable, str(Path(__file__).parents[1] / "scripts" / "average_checkpoints.py")]
    out = tmp_path / "soup.pt"
    chosen = ["--chosen-on", "real video frames"]
    done = subprocess.run(
        [*script, *map(str, paths), "--weights", "2/3,1/3", *chosen, "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    weights = [part["weight"] for part in load_checkpoint(out)["averaged_from"]]
    np.testing.assert_allclose(weights, [2 / 3, 1 / 3])
    assert load_checkpoint(out)["val_set"] == "real video frames"
    args = [str(tmp_path / "missing.pt"), str(paths[0]), "--weights", "2/3,1/3"]
    done = subprocess.run([*script, *args, "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 2 and "no such checkpoint" in done.stderr
    assert done.stderr.startswith("average_checkpoints: ") and done.stderr.count("\n") == 1


def test_averaged_checkpoint_holds_the_weighted_mean_and_says_of_what(tmp_path):
    """A soup of two checkpoints of one network is their weighted mean, parameter by parameter
    (so its output interpolates: the mean of a network with itself is that network); integer
    buffers and the metadata are the last source's, and ``averaged_from`` names the sources.
    Different networks, one source or weights that do not sum to 1 are refused."""
    config = get_config("tiny")
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        path = tmp_path / f"seed{seed}.pt"
        model = build_model(config).state_dict()
        save_checkpoint(
            path,
            model=model,
            config=config_to_dict(config),
            step=10 * (seed + 1),
            val_psnr=30.0,
            val_set="procedural" if seed == 0 else "natural",
        )
        paths.append(path)
    average_checkpoints(paths, [0.25, 0.75], tmp_path / "soup.pt")
    soup, state = read_network(tmp_path / "soup.pt")
    a, b = (read_network(p)[0].state_dict() for p in paths)
    for name, tensor in soup.state_dict().items():
        if tensor.is_floating_point():
            torch.testing.assert_close(tensor, 0.25 * a[name] + 0.75 * b[name])
        else:
            assert torch.equal(tensor, b[name])
    assert state["step"] == 20 and "val_psnr" not in state  # a score the mean was not given
    assert state["val_set"] == "natural"  # the last source's record, unless one is given
    assert state["averaged_from"] == [
        {"path": "seed0.pt", "step": 10, "weight": 0.25},
        {"path": "seed1.pt", "step": 20, "weight": 0.75},
    ]
    torch.manual_seed(2)
    third = tmp_path / "seed2.pt"
    save_checkpoint(third, model=build_model(config).state_dict(), config=config_to_dict(config))
    average_checkpoints([tmp_path / "soup.pt", third], [0.8, 0.2], tmp_path / "nested.pt")
    average_checkpoints([*paths, third], [0.2, 0.6, 0.2], tmp_path / "flat.pt")
    nested, flat = (load_checkpoint(tmp_path / f"{n}.pt") for n in ("nested", "flat"))
    for name, tensor in flat["model"].items():
        torch.testing.assert_close(nested["model"][name], tensor)
    assert [part["path"] for part in nested["averaged_from"]] == [
        "seed0.pt",
        "seed1.pt",
        "seed2.pt",
    ]
    weights = [part["weight"] for part in nested["averaged_from"]]
    np.testing.assert_allclose(weights, [0.2, 0.6, 0.2])  # a mean in a mean lists its sources

    average_checkpoints([paths[0], paths[0]], [0.5, 0.5], tmp_path / "self.pt")
    spikes = (torch.rand(1, 41, 24, 32) < 0.3).float()
    with torch.no_grad():
        torch.testing.assert_close(
            read_network(tmp_path / "self.pt")[0](spikes), read_network(paths[0])[0](spikes)
        )

    other = tmp_path / "lite.pt"
    lite = get_config("lite")
    save_checkpoint(other, model=build_model(lite).state_dict(), config=config_to_dict(lite))
    with pytest.raises(CheckpointError, match="a different network"):
        average_checkpoints([paths[0], other], [0.5, 0.5], tmp_path / "x.pt")
    with pytest.raises(InputError, match="two or more"):
        average_checkpoints(paths[:1], [1.0], tmp_path / "x.pt")
    with pytest.raises(InputError, match="sum to 1"):
        average_checkpoints(paths, [0.5, 0.6], tmp_path / "x.pt")


def test_a_released_checkpoint_keeps_the_network_and_what_it_was_chosen_on(tmp_path):
    """A release copies the weights and the run's record but not the optimiser state; with
    ``val_set`` (a step chosen after the run) the record is replaced and the run's own score,
    on another set, is dropped."""
    config = get_config("tiny")
    weights = build_model(config).state_dict()
    run = tmp_path / "best.pt"
    save_checkpoint(
        run,
        model=weights,
        config=config_to_dict(config),
        step=40,
        val_psnr=33.6,
        val_set="real video",
        optimizer={"state": {}, "param_groups": []},
    )
    release_checkpoint(run, tmp_path / "as-logged.pt")
    release_checkpoint(run, tmp_path / "chosen.pt", val_set="real video frames")
    logged, chosen = (load_checkpoint(tmp_path / f"{n}.pt") for n in ("as-logged", "chosen"))
    for state in (logged, chosen):
        assert "optimizer" not in state and state["step"] == 40
        for name, tensor in weights.items():
            assert torch.equal(state["model"][name], tensor)
    assert logged["val_set"] == "real video" and logged["val_psnr"] == 33.6
    assert chosen["val_set"] == "real video frames" and "val_psnr" not in chosen


def test_the_motion_stride_is_the_feature_strides_multiple_and_pads_for_the_motions_pyramid():
    """``motion_stride`` sets where the blocks' motion is found (0: the feature stride); the
    network pads to a multiple of its motion pyramid's too, only where it reads the motion."""
    small, cpu = MEMBERS["small"], MEMBERS["cpu"]
    assert cpu.size_multiple == 16 and cpu.motion_scale == 4  # as shipped
    assert replace(small, motion_stride=4, motion_levels=2).size_multiple == 4  # not read
    guided = replace(small, flow_guided=True, motion_stride=4, motion_levels=2)
    assert guided.size_multiple == 8 and guided.motion_scale == 4
    with pytest.raises(ValueError, match="motion_stride must be 0 or a multiple of feature"):
        replace(cpu, motion_stride=6)
    with pytest.raises(ValueError, match="motion_stride must be 0 or a multiple"):
        replace(small, motion_stride=-1)


def test_a_guided_full_size_member_upsamples_its_quarter_size_motion_and_stays_finite():
    """A full-size member guided by motion found at 1/4 size: on odd sizes and extreme inputs
    its output is finite and in range, and the motion reaching its alignment is the
    quarter-size one upsampled, each displacement four times as many pixels."""
    config = replace(
        MEMBERS["tiny"], flow_guided=True, motion_stride=4, motion_levels=2, motion_window=7
    )
    model = build_model(config).eval()
    torch.manual_seed(0)
    for spikes in (
        torch.zeros(1, 41, 19, 23),
        torch.ones(1, 41, 19, 23),
        (torch.rand(2, 41, 17, 30) < 0.3).float(),
    ):
        with torch.no_grad():
            image, _ = model(spikes)
        assert image.shape == (spikes.shape[0], 1, *spikes.shape[-2:])
        assert torch.isfinite(image).all() and 0 <= image.min() and image.max() <= 1
    weighted = torch.rand(1, 5, 3, 32, 48)
    quarter = block_motion(weighted, 1, 4, levels=2, window=7, damping=1e-3, iterations=3)
    upsampled = model.block_motion(weighted)
    assert quarter.shape == (4, 2, 8, 12) and upsampled.shape == (4, 2, 32, 48)
    expected = 4 * F.interpolate(quarter, scale_factor=4, mode="bilinear", align_corners=False)
    torch.testing.assert_close(upsampled, expected)
