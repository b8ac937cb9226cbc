"""The alignment term of the training loss (spk2img.training.alignment_loss, ``--align-weight``):
zero where the sampling follows the motion, its gradient pointing the offsets along it, and the
shifts it reads the ones the alignment probe reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from spk2img.evaluation.alignment_probe import neighbour_offsets, pan_spikes, sampling_shifts
from spk2img.model.network import build_model
from spk2img.training.alignment_loss import alignment_term, recorded_shifts
from spk2img.training.train import TrainConfig, train

SIZE = 64
TIMES = (-14, -7, 0, 7, 14)
"""Block centres relative to the key's, spike frames (the published geometry)."""


def panned_truth(speed: float, direction: int) -> torch.Tensor:
    """``(1, 5, SIZE, SIZE)`` a smooth texture at the block centres, moving ``speed`` px a frame
    along ``direction`` (0: y, 1: x)."""
    yy, xx = torch.meshgrid(torch.arange(SIZE).float(), torch.arange(SIZE).float(), indexing="ij")

    def at(t: float) -> torch.Tensor:
        y, x = (yy - speed * t, xx) if direction == 0 else (yy, xx - speed * t)
        return 0.5 + 0.2 * torch.sin(x / 3.1) * torch.cos(y / 4.3) + 0.2 * torch.sin((x + y) / 5.7)

    return torch.stack([at(t) for t in TIMES])[None]


def shifts_of(displacement: torch.Tensor, level: int, direction: int) -> torch.Tensor:
    """Mean shifts ``(4, 2, s, s)`` at ``level`` that sample each neighbour ``displacement``
    ``(4,)`` full-size px away along ``direction``."""
    scale = 2 ** (level - 1)
    shift = torch.zeros(4, 2, SIZE // scale, SIZE // scale)
    shift[:, direction] = displacement[:, None, None] / scale
    return shift


@settings(max_examples=12, deadline=None)
@given(st.floats(0.05, 0.3), st.integers(0, 1), st.integers(1, 3))
def test_the_term_is_least_where_the_sampling_follows_the_motion(speed, direction, level):
    truth = panned_truth(speed, direction)
    follows = torch.tensor([speed * t for t in TIMES if t])
    at_motion = alignment_term({level: shifts_of(follows, level, direction)}, truth, 1)
    still = shifts_of(torch.zeros(4), level, direction).requires_grad_()
    at_zero = alignment_term({level: still}, truth, 1)
    against = alignment_term({level: shifts_of(-follows, level, direction)}, truth, 1)
    assert float(at_motion) < 0.5 * float(at_zero.detach()) < 0.5 * float(against)
    at_zero.backward()
    # descending the gradient moves each neighbour's mean shift towards its displacement
    step = -still.grad[:, direction].mean(dim=(1, 2))
    assert torch.all(torch.sign(step) == torch.sign(follows))


def test_the_recorded_shifts_are_the_probes_and_stop_with_the_context():
    """The term reads each level's mean sampling shift as the alignment probe does (the same
    numbers, here with gradients), and a forward pass outside the context records nothing."""
    torch.manual_seed(0)
    model = build_model("tiny").eval()
    for conv in model.align.dcn_pack.values():  # offsets that vary with the content
        torch.nn.init.normal_(conv.conv_offset_mask.weight, std=0.05)
    source = np.random.default_rng(1).uniform(0.1, 0.9, (SIZE + 48, SIZE + 48)).astype(np.float32)
    spikes = pan_spikes(source, SIZE, SIZE, 0.5, seed=0)
    probe = sampling_shifts(model, spikes)
    with recorded_shifts(model) as shifts:
        model(torch.from_numpy(spikes[None].astype(np.float32)))
    assert sorted(shifts) == [1, 2] and all(s.requires_grad for s in shifts.values())
    assert len(neighbour_offsets(model)) == shifts[1].shape[0]
    for level, shift in shifts.items():
        inner = shift[..., 2:-2, 2:-2].mean(dim=(2, 3)).detach().double().numpy()
        np.testing.assert_allclose(inner, probe[f"align.dcn_pack.l{level}"], atol=1e-6)
        assert float(shift[:, 1].detach().abs().mean()) > 1e-3
    shifts.clear()
    with torch.no_grad():
        model(torch.from_numpy(spikes[None].astype(np.float32)))
    assert shifts == {}


def test_a_run_with_the_alignment_term_logs_it_and_trains_the_offsets(tmp_path):
    """``--align-weight`` adds the term to the loss: the log records it at every step, and the
    offset predictors, which start at zero, move."""
    run = tmp_path / "run"
    cfg = dict(member="tiny", patch=16, batch_size=2, val_every=100, val_per_class=1)
    cfg |= dict(log_every=1, progress=False, warmup_steps=1, workers=0, align_weight=1.0)
    train(TrainConfig(run_dir=str(run), steps=3, **cfg))
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    aligns = [r["align"] for r in records if r["kind"] == "train"]
    assert len(aligns) == 3 and all(np.isfinite(aligns)) and max(aligns) > 0
    weights = torch.load(run / "last.pt", weights_only=False)["model"]
    assert float(weights["align.dcn_pack.l2.conv_offset_mask.weight"].abs().max()) > 0


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_a_bad_alignment_weight_is_refused(weight):
    with pytest.raises(ValueError, match="--align-weight"):
        TrainConfig(align_weight=weight)
