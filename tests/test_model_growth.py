"""A trained member grown wider and deeper (spk2img.model.growth) computes what it did, and its
new channels learn."""

from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.export.onnx_export import random_source
from spk2img.model.config import MEMBERS, MOTION_FIELDS, PAPER
from spk2img.model.growth import grow_weights, growth_problems
from spk2img.model.network import build_model


def _grown(old, config) -> torch.nn.Module:
    new = build_model(config)
    grow_weights(new, old.state_dict(), old.config)
    return new


def _assert_same_outputs(old, new, spikes) -> None:
    for training in (False, True):
        with torch.no_grad():
            image, estimates = old.train(training)(spikes)
            grown_image, grown_estimates = new.train(training)(spikes)
        torch.testing.assert_close(grown_image, image, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(grown_estimates, estimates, atol=0, rtol=0)


def test_small_grown_into_medium_computes_what_small_did():
    torch.manual_seed(0)
    old = random_source("small", seed=0).model  # offsets random too: the sampling moves
    new = _grown(old, MEMBERS["medium"])
    spikes = (torch.rand(1, 41, 13, 22) < 0.3).float()  # not a multiple of 4: padded inside
    _assert_same_outputs(old, new, spikes)
    fresh = build_model("medium").eval()
    with torch.no_grad():  # the check can fail: a network not grown computes something else
        assert (fresh(spikes)[0] - new.eval()(spikes)[0]).abs().max() > 1e-3


@settings(max_examples=8, deadline=None)
@given(
    factor=st.integers(1, 3),
    mask_extra=st.integers(0, 6),
    fusion_extra=st.integers(0, 9),
    blocks_extra=st.integers(0, 2),
    seed=st.integers(0, 2**16),
)
def test_any_growth_of_widths_and_depth_computes_what_the_network_did(
    factor, mask_extra, fusion_extra, blocks_extra, seed
):
    """``tiny`` (a 2-level pyramid, 2 convs a residual block) widened by any whole factor,
    its masks' and fusion's hidden widths by any amount and its feature extractor by whole
    blocks, the same spike window gives the same image."""
    tiny = MEMBERS["tiny"]
    config = replace(
        tiny,
        channels=tiny.channels * factor,
        deformable_groups=tiny.deformable_groups * factor,
        reliability_hidden=tiny.reliability_hidden * factor + mask_extra,
        fusion_hidden=tiny.fusion_hidden + fusion_extra,
        residual_blocks=tiny.residual_blocks + blocks_extra,
    )
    torch.manual_seed(seed)
    old = random_source("tiny", seed=seed).model
    assert growth_problems(tiny, config) == []
    new = _grown(old, config)
    _assert_same_outputs(old, new, (torch.rand(1, 41, 10, 14) < 0.4).float())


def test_the_new_width_learns():
    """The zeros that keep the old channels from reading the new ones get gradients at once,
    and the new channels reach the image after one update."""
    torch.manual_seed(1)
    old = random_source("tiny", seed=1).model
    config = replace(old.config, channels=24, deformable_groups=4, residual_blocks=3)
    new = _grown(old, config).train()
    spikes = (torch.rand(2, 41, 12, 16) < 0.4).float()
    image, _ = new(spikes)
    image.mean().backward()
    head_conv = new.fusion.reconstruct[4].weight  # (1, c, 3, 3): the old 12 channels only
    assert (head_conv[:, 12:] == 0).all() and head_conv.grad[:, 12:].abs().sum() > 0
    cross = new.features.body[0].body[0].weight  # old outputs x new inputs
    assert cross.grad[:12, 12:].abs().sum() > 0
    added_block = new.features.body[2].body[2]  # the new block's last conv, at zero
    assert (added_block.weight == 0).all() and added_block.weight.grad.abs().sum() > 0
    torch.optim.SGD(new.parameters(), lr=0.1).step()
    with torch.no_grad():
        new.eval()(spikes)
        moved = new.fusion.reconstruct[4].weight[:, 12:].abs().sum()
    assert moved > 0


def test_a_guided_member_grows_offset_convs_that_read_its_motion():
    """A motion-guided ``cpu`` (random weights, its sampling guided and moving) grows the convs
    by which each pyramid level's offsets read the blocks' motion: they start at zero, so on a
    moving stream the grown network computes what it did, and they get a gradient at once; the
    step back (dropping them) is refused."""
    cpu = MEMBERS["cpu"]
    reading = replace(cpu, offsets_read_motion=True)
    assert growth_problems(cpu, reading) == []
    old = random_source(cpu, seed=4).model
    new = _grown(old, reading)
    assert all(
        not conv.weight.any() and not conv.bias.any() for conv in new.align.motion_conv.values()
    )
    frames = torch.rand(1, 1, 24, 48, generator=torch.Generator().manual_seed(5)) < 0.3
    pan = torch.cat([frames.roll(t // 4, dims=-1) for t in range(41)], dim=1).float()
    _assert_same_outputs(old, new, pan)
    new.train()(pan)[0].square().mean().backward()
    assert all(conv.weight.grad.abs().max() > 0 for conv in new.align.motion_conv.values())
    assert any("offsets_read_motion would shrink" in p for p in growth_problems(reading, cpu))


def test_offsets_read_the_motion_only_where_it_guides_them():
    with pytest.raises(ValueError, match="needs the motion to guide them"):
        replace(MEMBERS["tiny"], offsets_read_motion=True)
    net = build_model(replace(MEMBERS["tiny"], flow_guided=True, offsets_read_motion=True))
    pyramid = [torch.zeros(1, 12, 8, 8), torch.zeros(1, 12, 4, 4)]
    with pytest.raises(ValueError, match="give its flow"):
        net.align(pyramid, pyramid, None)


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        ({"channels": 12, "deformable_groups": 2}, "channels, deformable_groups would shrink"),
        ({"channels": 48, "deformable_groups": 4}, "channels per deformable group"),
        ({"fusion_hidden": 64}, "fusion_hidden would shrink"),
        ({"residual_blocks": 2}, "residual_blocks would shrink"),
        ({"pyramid_levels": 2}, "pyramid_levels 3 -> 2"),
        ({"sali_hidden": 32}, "sali_hidden 16 -> 32"),
    ],
)
def test_what_cannot_grow_is_named(change, problem):
    small = MEMBERS["small"]
    config = replace(small, **change)
    assert any(problem in line for line in growth_problems(small, config))
    with pytest.raises(ValueError, match=problem):
        grow_weights(build_model(config), build_model("small").state_dict(), small)


def test_equal_shapes_are_not_a_growth_and_bad_weights_are_refused():
    small = MEMBERS["small"]
    assert growth_problems(small, small) == []
    weights = build_model("small").state_dict()
    with pytest.raises(ValueError, match="lacks: extra"):
        grow_weights(build_model("medium"), weights | {"extra": torch.zeros(1)}, small)
    missing = {k: v for k, v in weights.items() if not k.startswith("fusion.reconstruct.4")}
    with pytest.raises(ValueError, match="no stored weights for fusion.reconstruct.4"):
        grow_weights(build_model("medium"), missing, small)
    old_block = {k: v for k, v in weights.items() if not k.startswith("features.body.1.")}
    with pytest.raises(ValueError, match="no stored weights for features.body.1.body.0"):
        grow_weights(build_model("medium"), old_block, small)


def test_the_motions_settings_change_freely_and_keep_every_weight():
    """``cpu`` (one-level Lucas-Kanade, the settings its checkpoints stored before the motion's
    fields, which they are read with) goes to two levels and other dampings: no weight to grow,
    each one loaded as it was."""
    cpu = MEMBERS["cpu"]
    assert all(getattr(cpu, name) == getattr(PAPER, name) for name in MOTION_FIELDS)
    two_levels = replace(
        cpu,
        motion_levels=2,
        motion_window=15,
        motion_damping=1e-6,
        motion_damping_per_intensity=1e-3,
        motion_iterations=4,
    )
    assert growth_problems(cpu, two_levels) == []
    old = random_source(cpu, seed=1).model
    new = _grown(old, two_levels)
    for name, weight in old.state_dict().items():
        assert torch.equal(new.state_dict()[name], weight), name


def test_cpu_grown_in_width_and_by_its_detail_refinement_at_once():
    """A ``cpu`` half as wide, with a narrower, shallower refinement that the blocks' motion did
    not yet guide, grows into ``cpu`` in one step: on a still scene (the motion is zero, the
    grown refinement adds what the old one did) the image is the old network's."""
    cpu = MEMBERS["cpu"]
    stored = replace(
        cpu, channels=16, deformable_groups=1, detail_hidden=24, detail_depth=1, flow_guided=False
    )
    torch.manual_seed(2)
    old = build_model(stored).eval()
    old.detail.body[-1].reset_parameters()  # as trained: the refinement adds something
    assert growth_problems(stored, cpu) == []
    new = _grown(old, cpu).eval()
    still = (torch.rand(1, 7, 20, 36, generator=torch.Generator().manual_seed(3)) < 0.3).float()
    spikes = still.repeat(1, 6, 1, 1)[:, :41]  # period 7: the five blocks are equal
    with torch.no_grad():
        image, fresh = old(spikes)[0], build_model("cpu").eval()(spikes)[0]
        torch.testing.assert_close(new(spikes)[0], image, atol=1e-6, rtol=1e-5)
    assert (fresh - image).abs().max() > 1e-3


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        ({"detail_hidden": 0, "detail_aligned": False, "flow_guided": False}, "would be removed"),
        ({"detail_depth": 1}, "detail_depth would shrink"),
        ({"flow_guided": False}, "flow_guided would shrink"),
    ],
)
def test_a_detail_refinement_undone_is_named(change, problem):
    cpu = MEMBERS["cpu"]
    config = replace(cpu, **change)
    assert growth_problems(config, cpu) == []
    assert any(problem in line for line in growth_problems(cpu, config))


def test_a_checkpoint_without_its_detail_refinement_is_refused():
    """Weights of a ``cpu`` that had a refinement but lack it are not taken for one without."""
    cpu = MEMBERS["cpu"]
    stored = replace(cpu, detail_hidden=24, detail_depth=1)
    cut = {k: v for k, v in build_model(stored).state_dict().items() if not k.startswith("detail.")}
    with pytest.raises(ValueError, match="no stored weights for the detail refinement"):
        grow_weights(build_model(cpu), cut, stored)
