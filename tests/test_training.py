import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from onnx_models import write_tiny_checkpoint
from PIL import Image

from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.evaluation.real_video import film, real_video_scenes, save_windows
from spk2img.evaluation.scoring import validation_set
from spk2img.model.checkpoint import (
    config_to_dict,
    load_checkpoint,
    load_model,
    release_checkpoint,
    save_checkpoint,
)
from spk2img.model.config import MOTION_FIELDS, PUBLISHED_GEOMETRY, get_config
from spk2img.model.network import Spk2ImgNet, build_model
from spk2img.runtime.torch_backend import DEFAULT_CHECKPOINT
from spk2img.sim.scenes import MOTIONS, TRAINING_MOTIONS, draw_speed, random_scene
from spk2img.sim.simulator import FILM_FRAMES, SensorConfig
from spk2img.sim.sources import load_photo
from spk2img.training.data import KINDS, Batches, SampleMaker, speed_weights
from spk2img.training.ema import WeightAverage
from spk2img.training.loss import hierarchical_loss
from spk2img.training.stop import StopRequest
from spk2img.training.synthesis import batch_generator, film_plans
from spk2img.training.train import (
    TrainConfig,
    learning_rate,
    load_initial_weights,
    logged_best,
    train,
    validate,
)

TINY_RUN = dict(
    member="tiny",
    patch=16,
    batch_size=2,
    val_every=4,
    val_per_class=1,
    checkpoint_every=2,
    log_every=1,
    progress=False,
    warmup_steps=2,
    workers=0,
)


def _records(run_dir, kind):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["kind"] == kind]


@pytest.mark.parametrize(
    ("final", "expected"), [("l1", 0.1 + 0.02 * 20 * 0.5), ("psnr", -20 + 0.02 * 20 * 0.5)]
)
def test_loss_is_the_final_term_plus_weighted_intermediate_l1(final, expected):
    """An error of 0.1 everywhere: L1 0.1, PSNR 20 dB (the 1e-6 floor moves it by 4e-4 dB)."""
    truth = torch.rand(2, 5, 8, 8)
    image = truth[:, 2:3] + 0.1
    estimates = truth.unsqueeze(2).expand(2, 5, 4, 8, 8) - 0.5
    loss = hierarchical_loss(image, estimates, truth, final)
    assert loss.item() == pytest.approx(expected, abs=1e-3)


def test_the_psnr_term_weighs_each_window_by_its_own_error():
    """Minus the mean PSNR: halving the error of a good window gains as much as halving that of
    a bad one, where the squared error would barely see the good one."""
    truth = torch.zeros(2, 5, 8, 8)
    estimates = truth.unsqueeze(2).expand(2, 5, 4, 8, 8)
    image = torch.tensor([0.05, 0.4]).view(2, 1, 1, 1).expand(2, 1, 8, 8)
    better_good = image * torch.tensor([0.5, 1.0]).view(2, 1, 1, 1)
    better_bad = image * torch.tensor([1.0, 0.5]).view(2, 1, 1, 1)
    gains = [
        (
            hierarchical_loss(image, estimates, truth, "psnr")
            - hierarchical_loss(i, estimates, truth, "psnr")
        ).item()
        for i in (better_good, better_bad)
    ]
    assert gains[0] == pytest.approx(gains[1], rel=0.01)
    assert gains[0] == pytest.approx(10 * np.log10(4) / 2, rel=0.01)


def test_an_unknown_loss_is_refused(tmp_path, capsys):
    assert main(["train", "--run-dir", str(tmp_path / "run"), "--loss", "l2"]) == 2
    assert "--loss l2: use one of l1, psnr" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flag, value, says",
    [
        ("--steps", "-1", "--steps -1: must be >= 1"),
        ("--warmup-steps", "-5", "--warmup-steps -5: must be >= 0"),
        ("--batch-size", "0", "--batch-size 0: must be >= 1"),
        ("--patch", "0", "--patch 0: must be >= 4"),
        ("--workers", "-1", "--workers -1: must be >= 0"),
        ("--val-every", "0", "--val-every 0: must be >= 1"),
        ("--checkpoint-every", "0", "--checkpoint-every 0: must be >= 1"),
        ("--threads", "0", "--threads 0: must be >= 1"),
        ("--lr", "-1", "--lr -1.0: must be a positive number"),
        ("--lr", "nan", "--lr nan: must be a positive number"),
        ("--data-mix", "photos=nan", "bad data mix 'photos=nan'"),
        ("--data-mix", "photos=inf", "bad data mix 'photos=inf'"),
        ("--speed-mix", "slow=-1", "'slow=-1': classes are static, slow, fast, moderate"),
        ("--speed-mix", "walk=1", "bad speed mix 'walk=1'"),
        ("--speed-mix", "slow", "bad speed mix 'slow': use e.g. static=0.5,slow=0.5"),
        ("--motion", "levels=2", "--motion levels=2: tiny does not read the blocks' motion"),
    ],
)
def test_a_flag_out_of_its_range_is_one_line_before_any_work(tmp_path, capsys, flag, value, says):
    run = tmp_path / "run"
    assert main(["train", "--run-dir", str(run), "--no-progress", f"{flag}={value}"]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not run.exists()


def test_batches_are_a_function_of_seed_and_step():
    a = SampleMaker(16, seed=3).batch(5, 2)
    b = SampleMaker(16, seed=3).batch(5, 2)
    c = SampleMaker(16, seed=3, rank=1).batch(5, 2)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    assert a[0].shape == (2, 41, 16, 16) and a[1].shape == (2, 5, 16, 16)
    assert set(np.unique(a[0])) <= {0.0, 1.0}


@settings(max_examples=15, deadline=None)
@given(
    shares=st.tuples(*[st.sampled_from([0.0, 0.1, 0.5, 1.0, 3.0])] * 4).filter(lambda s: sum(s) > 0)
)
def test_the_speed_mix_sets_how_often_each_motion_class_is_drawn(shares):
    """``--speed-mix``: each motion class, ``moderate`` included, is drawn in proportion to its
    share (400 draws, within 0.08), a class of share 0 never; a mix without ``moderate`` draws
    as it did before that class existed (equal shares of the three as a maker without a mix,
    scene for scene)."""
    text = ",".join(f"{n}={share}" for n, share in zip(TRAINING_MOTIONS, shares, strict=True))
    maker = SampleMaker(16, seed=5, speeds=speed_weights(text))
    drawn = [maker.draw(step, 0)[1].meta["motion"] for step in range(400)]
    for name, share in zip(TRAINING_MOTIONS, shares, strict=True):
        assert drawn.count(name) / 400 == pytest.approx(share / sum(shares), abs=0.08)
        assert share or name not in drawn
    if shares[3] == 0:  # the draw before moderate existed, replayed
        three = np.array(shares[:3]) / sum(shares[:3])

        def before(step):
            rng = np.random.default_rng([5, 0, step, 0])
            rng.choice(len(KINDS), p=maker.weights)
            return str(
                rng.choice(MOTIONS) if len(set(shares[:3])) == 1 else rng.choice(MOTIONS, p=three)
            )

        assert drawn == [before(step) for step in range(400)]


def test_moderate_scenes_move_between_the_slow_and_fast_classes():
    """A ``moderate`` scene moves 0.3-1 px a spike frame (log-uniform: both halves of the range
    drawn), procedural and photo alike; the default draws never give it."""
    rng = np.random.default_rng(3)
    speeds = [random_scene(rng, 32, 32, "moderate").meta["speed"] for _ in range(60)]
    assert min(speeds) >= 0.3 and max(speeds) <= 1.0
    assert min(speeds) < np.sqrt(0.3) < max(speeds)
    assert all(draw_speed(rng, "moderate") >= 0.3 for _ in range(50))
    defaults = {random_scene(rng, 16, 16).meta["motion"] for _ in range(60)}
    assert defaults == set(MOTIONS)


def test_the_ideal_share_sets_how_many_samples_the_noise_free_sensor_films():
    """``ideal_share`` 1: every sample noise-free; 0: every one real-like; 0.5 about half.
    A share outside [0, 1] is refused (the CLI turns it into a message)."""
    real = SensorConfig.real()
    for share, expected in ((1.0, 1.0), (0.0, 0.0), (0.5, 0.5)):
        maker = SampleMaker(16, seed=0, real_sensor=real, ideal_share=share)
        rngs = (np.random.default_rng([9, k]) for k in range(400))
        ideal = np.mean([maker.draw_sensor(rng) == SensorConfig.ideal() for rng in rngs])
        assert ideal == pytest.approx(expected, abs=0.08)
    with pytest.raises(ValueError, match="ideal-share"):
        TrainConfig(ideal_share=1.5)
    with pytest.raises(ValueError, match="ideal-share"):
        SampleMaker(16, seed=0, ideal_share=-0.5)
    assert main(["train", "--ideal-share", "-0.1", "--steps", "1"]) == 2


def test_worker_processes_make_the_same_batches_in_order():
    maker = SampleMaker(16, seed=4)
    batches = Batches(maker, 2, start=7, workers=1)
    try:
        made = [batches.next() for _ in range(3)]
    finally:
        batches.close()
    for step, (spikes, truth) in enumerate(made, start=7):
        expected = maker.batch(step, 2)
        assert np.array_equal(spikes, expected[0]) and np.array_equal(truth, expected[1])


def test_worker_processes_draw_the_same_scene_plans_in_order():
    """Plans made in a worker process and sent back film to the same batches as plans made
    here (torch synthesis)."""
    maker = SampleMaker(16, seed=4)
    batches = Batches(maker, 2, start=7, workers=1, make="plans")
    try:
        made = [batches.next() for _ in range(2)]
    finally:
        batches.close()
    for step, plans in enumerate(made, start=7):
        generator = batch_generator(4, 0, step, torch.device("cpu"))
        spikes, truth = film_plans(plans, PUBLISHED_GEOMETRY, generator)
        generator = batch_generator(4, 0, step, torch.device("cpu"))
        expected = film_plans(maker.plans(step, 2), PUBLISHED_GEOMETRY, generator)
        assert torch.equal(spikes, expected[0]) and torch.equal(truth, expected[1])


@pytest.mark.parametrize("synthesis, ema_decay", [("numpy", 0.0), ("torch", 0.5)])
def test_resume_continues_the_same_loss_curve(tmp_path, synthesis, ema_decay):
    """Either simulator: a run stopped at step 3 and resumed ends where a straight one does,
    with the same weight average (``--ema-decay``) where it keeps one."""
    run = TINY_RUN | {"synthesis": synthesis, "ema_decay": ema_decay}
    straight = tmp_path / "straight"
    train(TrainConfig(run_dir=str(straight), steps=6, **run))
    resumed = tmp_path / "resumed"
    train(TrainConfig(run_dir=str(resumed), steps=3, **run))
    assert load_checkpoint(resumed / "last.pt")["step"] == 3
    train(TrainConfig(run_dir=str(resumed), steps=6, **run))
    a = [r["loss"] for r in _records(straight, "train")]
    b = [r["loss"] for r in _records(resumed, "train")]
    assert len(a) == len(b) == 6
    np.testing.assert_allclose(a, b, rtol=1e-5)
    starts = _records(resumed, "run")  # one at each (re)start, with what trains
    assert [r["step"] for r in starts] == [0, 3]
    assert all(r["train_config"]["batch_size"] == 2 and r["member"] == "tiny" for r in starts)
    assert all("CPU" in r["hardware"] and r["init_from"] is None for r in starts)
    last_a, last_b = (load_checkpoint(r / "last.pt") for r in (straight, resumed))
    assert ("ema" in last_a) == ("ema" in last_b) == bool(ema_decay)
    for weights in ("model", "ema") if ema_decay else ("model",):
        for name, tensor in last_a[weights].items():
            torch.testing.assert_close(last_b[weights][name], tensor, rtol=1e-5, atol=1e-6)


def test_a_resumed_run_without_its_best_pt_keeps_the_logged_best(tmp_path):
    """The repository keeps a run's last.pt alone: resumed without best.pt, a run writes it only
    for a validation that beats every one its log records before (here a doctored 99 dB)."""
    run = tmp_path / "run"
    train(TrainConfig(run_dir=str(run), steps=2, **TINY_RUN | {"val_every": 2}))
    assert load_checkpoint(run / "best.pt")["step"] == 2
    (run / "best.pt").unlink()
    lines = (run / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    for record in records:
        if record["kind"] == "val" and record["step"] == 2:
            record["psnr"] = 99.0
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    summary = train(TrainConfig(run_dir=str(run), steps=4, **TINY_RUN | {"val_every": 2}))
    assert [r["step"] for r in _records(run, "val")] == [2, 4]
    assert not (run / "best.pt").exists() and summary["best_psnr"] == 99.0
    assert summary["best_checkpoint"] is None


def test_logged_best_reads_the_selection_score_up_to_the_resumed_step(tmp_path):
    log = tmp_path / "metrics.jsonl"
    rows = [
        {"kind": "train", "step": 1, "loss": 0.5},
        {"kind": "val", "step": 2, "psnr": 30.0, "real_video": {"psnr": 33.1}},
        {"kind": "val", "step": 4, "psnr": 29.0, "real_video": {"psnr": 33.3}},
        {"kind": "val", "step": 6, "psnr": 31.0},  # validated without the real-video set
        {"kind": "val", "step": 8, "psnr": 35.0, "real_video": {"psnr": 34.0}},  # after
    ]
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert logged_best(log, "real video", 6) == 33.3
    assert logged_best(log, "procedural", 6) == 31.0
    assert logged_best(log, "procedural", 8) == 35.0
    assert logged_best(log, "procedural", 1) == -math.inf
    assert logged_best(tmp_path / "none.jsonl", "procedural", 6) == -math.inf


def test_weight_average_follows_the_recurrence_and_copies_integer_buffers():
    """After each update: average = decay * average + (1 - decay) * weights, per tensor."""
    torch.manual_seed(0)
    model = build_model("tiny")
    average = WeightAverage(model, 0.9)
    expected = {k: v.clone() for k, v in model.state_dict().items()}
    for _ in range(3):
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.add_(torch.randn_like(parameter))
        average.update(model)
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point():
                expected[name] = 0.9 * expected[name] + 0.1 * tensor
            else:
                expected[name] = tensor.clone()
    for name, tensor in average.model.state_dict().items():
        torch.testing.assert_close(tensor, expected[name])
    assert not any(p.requires_grad for p in average.model.parameters())
    with pytest.raises(ValueError, match="decay"):
        WeightAverage(model, 1.0)


@pytest.mark.parametrize("decay", [1.5, -0.1])
def test_ema_decay_outside_its_range_is_refused(decay):
    with pytest.raises(ValueError, match="--ema-decay"):
        TrainConfig(ema_decay=decay)


def test_a_run_with_ema_validates_and_keeps_the_average(tmp_path):
    """``--ema-decay``: last.pt holds the trained weights and their average (``ema``), the
    validation scores the average and best.pt holds it (a resumed run continues the average:
    test_resume_continues_the_same_loss_curve)."""
    run = TINY_RUN | {"ema_decay": 0.5, "val_every": 4}
    train(TrainConfig(run_dir=str(tmp_path), steps=4, **run))
    last, best = (load_checkpoint(tmp_path / f"{n}.pt") for n in ("last", "best"))
    assert best["step"] == 4 and last["model"].keys() == last["ema"].keys()
    assert any(not torch.equal(last["model"][k], last["ema"][k]) for k in last["model"])
    for name, tensor in last["ema"].items():
        assert torch.equal(best["model"][name], tensor)
    networks = {}
    for weights in ("model", "ema"):
        networks[weights] = build_model("tiny")
        networks[weights].load_state_dict(last[weights])
    scenes = validation_set(run["val_per_class"])
    logged = _records(tmp_path, "val")[-1]["psnr"]
    assert logged == pytest.approx(validate(networks["ema"], scenes)["psnr"], abs=1e-6)
    assert logged != pytest.approx(validate(networks["model"], scenes)["psnr"], abs=1e-6)


def test_a_run_resumes_only_with_the_shape_that_started_it(tmp_path):
    """A ``last.pt`` of another shape than the member's (say, from before a member changed)
    is refused, not loaded into a network it does not describe."""
    train(TrainConfig(run_dir=str(tmp_path), steps=1, **TINY_RUN))
    state = load_checkpoint(tmp_path / "last.pt")
    state["config"]["channels"] = 16
    save_checkpoint(tmp_path / "last.pt", **state)
    with pytest.raises(InputError, match="another shape"):
        train(TrainConfig(run_dir=str(tmp_path), steps=2, **TINY_RUN))


@pytest.mark.parametrize(
    "settings, says",
    [
        ("speed=2", "use NAME=VALUE with NAME one of guided, read, levels, window"),
        ("guided=0,read=1", "offsets_read_motion needs the motion to guide them"),
        ("guided=yes", "'yes' is not 0 or 1"),
        ("levels", "use NAME=VALUE"),
        ("levels=two", "'two' is not an integer"),
        ("damping=lots", "'lots' is not a number"),
        ("window=4", "motion_window must be odd"),
        ("levels=4", "motion_levels must be 1 .. pyramid_levels=3"),
    ],
)
def test_bad_motion_settings_are_one_line_naming_them(tmp_path, capsys, settings, says):
    run = tmp_path / "run"
    argv = ["train", "--member", "cpu", "--run-dir", str(run), "--motion", settings]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--motion {settings}: " in err and says in err and "Traceback" not in err
    assert not run.exists()


def test_motion_settings_train_the_member_with_that_motion_and_resume_only_with_it(tmp_path):
    """``--motion`` changes the blocks' Lucas-Kanade motion and nothing else: the run starts
    from the same weights (``--init``: the motion has none), its checkpoints store the settings
    (an export reads them), and it resumes only with the settings it started with."""
    settings = "levels=2,window=15,damping=1e-4,damping_per_intensity=1e-3,iterations=4"
    cpu = TINY_RUN | {"member": "cpu", "val_every": 100}
    source = tmp_path / "source"
    train(TrainConfig(run_dir=str(source), steps=1, **cpu))
    moved = tmp_path / "moved"
    run = cpu | {"run_dir": str(moved), "init": str(source / "last.pt"), "motion": settings}
    train(TrainConfig(steps=1, **run))
    config = load_model(moved / "last.pt").config
    assert (config.motion_levels, config.motion_window, config.motion_iterations) == (2, 15, 4)
    assert (config.motion_damping, config.motion_damping_per_intensity) == (1e-4, 1e-3)
    shipped_motion = {name: getattr(get_config("cpu"), name) for name in MOTION_FIELDS}
    assert dataclasses.replace(config, **shipped_motion) == get_config("cpu")
    assert load_checkpoint(moved / "last.pt")["init_from"]["step"] == 1
    with pytest.raises(InputError, match="other motion settings.*--motion it was started with"):
        train(TrainConfig(steps=2, **run | {"motion": ""}))
    train(TrainConfig(steps=2, **run))
    assert load_checkpoint(moved / "last.pt")["step"] == 2


def test_init_starts_a_run_from_another_runs_weights(tmp_path):
    """``--init``: the new run's first loss is the old run's loss on the same batch with the
    old weights; the checkpoints say where the weights came from; another shape is refused."""
    source = tmp_path / "source"
    train(TrainConfig(run_dir=str(source), steps=3, **TINY_RUN))
    tuned = tmp_path / "tuned"
    train(TrainConfig(run_dir=str(tuned), steps=2, init=str(source / "last.pt"), **TINY_RUN))
    model = load_model(source / "last.pt")
    spikes, truth = (torch.from_numpy(a) for a in SampleMaker(16, seed=0).batch(0, 2))
    with torch.no_grad():
        expected = hierarchical_loss(*model.train()(spikes), truth).item()
    assert _records(tuned, "train")[0]["loss"] == pytest.approx(expected, rel=1e-4)
    state = load_checkpoint(tuned / "last.pt")
    assert state["step"] == 2 and state["init_from"]["step"] == 3
    assert state["init_from"]["path"] == str(source / "last.pt")
    assert state["init_from"]["run"] == "source"  # the run folder that wrote the weights
    assert _records(tuned, "run")[0]["init_from"] == state["init_from"]
    small = TINY_RUN | {"member": "small", "run_dir": str(tmp_path / "x")}
    with pytest.raises(InputError, match="another shape"):
        train(TrainConfig(steps=1, init=str(source / "last.pt"), **small))
    missing = TINY_RUN | {"run_dir": str(tmp_path / "y"), "init": str(tmp_path / "no.pt")}
    with pytest.raises(InputError, match="no such checkpoint"):
        train(TrainConfig(steps=1, **missing))
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint")
    garbage = missing | {"init": str(tmp_path / "garbage.pt")}
    with pytest.raises(InputError, match="not a spk2img training checkpoint"):
        train(TrainConfig(steps=1, **garbage))
    corrupt_run = tmp_path / "corrupt"  # a run to resume whose last.pt was cut short
    corrupt_run.mkdir()
    (corrupt_run / "last.pt").write_bytes((source / "last.pt").read_bytes()[:1000])
    with pytest.raises(InputError, match="last.pt: not a spk2img training checkpoint"):
        train(TrainConfig(steps=1, **TINY_RUN | {"run_dir": str(corrupt_run)}))
    weights_only = tmp_path / "weights-only"  # a committed state without Adam's moments
    release_checkpoint(source / "last.pt", weights_only / "last.pt")
    with pytest.raises(InputError, match="weights only, no optimiser state.*--init"):
        train(TrainConfig(steps=4, **TINY_RUN | {"run_dir": str(weights_only)}))
    tuned_on = TINY_RUN | {"run_dir": str(tmp_path / "on"), "init": str(weights_only / "last.pt")}
    train(TrainConfig(steps=1, **tuned_on))  # what the message says works
    resumed = load_checkpoint(tmp_path / "on" / "last.pt")
    assert resumed["step"] == 1 and resumed["init_from"]["path"] == str(weights_only / "last.pt")


def test_init_grows_the_shipped_default_into_medium(tmp_path):
    """``--member medium --init spk2img-default.pt`` (a ``small`` checkpoint): the grown
    network's loss is the shipped model's on the same batch, and where the weights came from is
    recorded; a checkpoint that cannot grow into ``medium`` is refused, naming why."""
    medium = build_model("medium")
    origin = load_initial_weights(medium, str(DEFAULT_CHECKPOINT))
    assert origin["member"] == "small" and origin["path"] == str(DEFAULT_CHECKPOINT)
    spikes, truth = (torch.from_numpy(a) for a in SampleMaker(16, seed=0).batch(0, 2))
    with torch.no_grad():
        expected = hierarchical_loss(*load_model(DEFAULT_CHECKPOINT).train()(spikes), truth)
        grown = hierarchical_loss(*medium.train()(spikes), truth)
    assert grown.item() == pytest.approx(expected.item(), rel=1e-5)
    tiny = write_tiny_checkpoint(tmp_path / "tiny.pt")
    with pytest.raises(InputError, match="cannot grow into: only the widths, .*pyramid_levels"):
        load_initial_weights(build_model("medium"), str(tiny))


def test_a_run_validates_on_real_video_windows_from_a_file(tmp_path):
    """``--real-video-windows``: the windows are scored at each validation as filmed ones are
    (and chose best.pt: the noise-free run's selection set); a file that is not one is an input
    error before any step."""
    rng = np.random.default_rng(3)
    frames = tuple(np.roll(rng.integers(0, 256, (48, 56), np.uint8), k, axis=1) for k in range(4))
    scenes = real_video_scenes("vid4_walk", frames, ("fast",), FILM_FRAMES)
    windows = [film(scene, 0) for scene in scenes]  # 16x24 inside the flow's margin
    path = tmp_path / "windows.npz"
    save_windows(windows, path)
    run = TINY_RUN | {"run_dir": str(tmp_path / "run"), "ideal_share": 1.0}
    train(TrainConfig(steps=4, real_video_windows=str(path), **run))
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    (data,) = [r for r in records if r["kind"] == "data"]
    (val,) = [r for r in records if r["kind"] == "val"]
    assert data["real_video_windows"] == 1 and 0 < val["real_video"]["psnr"] < 60
    # beside it, how far the alignment follows a pan: one finite slope per deformable conv
    slopes = val["alignment_slopes"]
    assert "align.cas_dcn_pack" in slopes and all(np.isfinite(v) for v in slopes.values())
    bad = TINY_RUN | {"run_dir": str(tmp_path / "bad"), "real_video_windows": str(tmp_path)}
    with pytest.raises(InputError, match="--real-video-windows .*not a file of real-video windows"):
        train(TrainConfig(steps=1, **bad))


def test_fp16_weights_start_a_run_as_the_weights_they_round(tmp_path):
    """A larger member's state is committed as fp16 weights alone (half the bytes):
    ``--init`` loads them into the fp32 network exactly as rounded, into the same member and
    grown into a wider one, and the grown network's loss is the fp16 checkpoint's."""
    half = tmp_path / "default-fp16.pt"
    release_checkpoint(DEFAULT_CHECKPOINT, half, torch.float16)
    stored = load_checkpoint(half)["model"]
    assert {t.dtype for t in stored.values() if t.is_floating_point()} == {torch.float16}
    assert half.stat().st_size < 0.6 * DEFAULT_CHECKPOINT.stat().st_size
    small = build_model("small")
    load_initial_weights(small, str(half))
    for name, tensor in small.state_dict().items():
        assert tensor.dtype == torch.float32
        torch.testing.assert_close(tensor, stored[name].to(tensor.dtype), rtol=0, atol=0)
    medium = build_model("medium")
    load_initial_weights(medium, str(half))
    spikes, truth = (torch.from_numpy(a) for a in SampleMaker(16, seed=1).batch(0, 2))
    with torch.no_grad():
        expected = hierarchical_loss(*small.train()(spikes), truth)
        grown = hierarchical_loss(*medium.train()(spikes), truth)
        shipped = hierarchical_loss(*load_model(DEFAULT_CHECKPOINT).train()(spikes), truth)
    assert grown.item() == pytest.approx(expected.item(), rel=1e-5)
    assert grown.item() != shipped.item() and grown.item() == pytest.approx(shipped.item(), 1e-2)


@pytest.mark.parametrize(
    "detail",
    [(0, 1, False), (24, 1, True), (48, 2, False)],
    ids=["without", "narrower", "unaligned"],
)
def test_init_grows_a_member_by_its_detail_refinement(tmp_path, detail):
    """A ``cpu`` checkpoint from before the member had its detail refinement, or had a narrower
    and shallower one, or one that read the blocks unaligned, or before the blocks' motion
    guided its alignment, starts a run of ``cpu``: every weight it holds is loaded and what the
    network gains starts where it changes nothing on a still scene (no motion, a refinement
    that adds nothing), so there the grown network computes what the checkpoint's did; weights
    that do not fit are refused."""
    hidden, depth, aligned = detail
    plain_config = dataclasses.replace(
        get_config("cpu"),
        detail_hidden=hidden,
        detail_depth=depth,
        detail_aligned=aligned,
        flow_guided=False,
    )
    torch.manual_seed(0)
    plain = Spk2ImgNet(plain_config).eval()
    if plain.detail is not None:
        plain.detail.body[-1].reset_parameters()  # as trained: the refinement adds something
    save_checkpoint(
        tmp_path / "plain.pt", model=plain.state_dict(), config=config_to_dict(plain_config)
    )
    grown = build_model("cpu").eval()
    assert grown.config != plain_config and grown.config.flow_guided
    load_initial_weights(grown, str(tmp_path / "plain.pt"))
    same_refinement = (grown.config.detail_hidden, grown.config.detail_depth) == (hidden, depth)
    grown_weights = grown.state_dict()
    for name, value in plain.state_dict().items():  # a grown refinement's: by its output
        if same_refinement or not name.startswith("detail."):
            assert torch.equal(grown_weights[name], value), name
    spikes = (torch.rand(2, 7, 20, 36, generator=torch.Generator().manual_seed(1)) < 0.3).float()
    spikes = spikes.repeat(1, 6, 1, 1)[:, :41]  # period 7: the five blocks are equal
    with torch.no_grad():
        torch.testing.assert_close(grown(spikes)[0], plain(spikes)[0])
    weights = plain.state_dict()
    del weights["fusion.reconstruct.0.bias"]
    save_checkpoint(tmp_path / "cut.pt", model=weights, config=config_to_dict(plain_config))
    with pytest.raises(InputError, match="no stored weights for fusion.reconstruct.0.bias"):
        load_initial_weights(build_model("cpu"), str(tmp_path / "cut.pt"))


def test_validation_logs_network_and_baselines(tmp_path):
    train(TrainConfig(run_dir=str(tmp_path), steps=4, **TINY_RUN))
    (base,) = _records(tmp_path, "baselines")
    assert np.isfinite(base["tfp_best"]["psnr"]) and np.isfinite(base["tfi"]["psnr"])
    (val,) = _records(tmp_path, "val")
    assert np.isfinite(val["psnr"]) and -1 <= val["ssim"] <= 1
    model = load_model(tmp_path / "best.pt")
    assert not model.training


def test_learning_rate_schedule():
    cfg = TrainConfig(steps=1000, lr=1e-3, warmup_steps=100)
    assert learning_rate(cfg, 0) == pytest.approx(1e-5)
    assert learning_rate(cfg, 99) == pytest.approx(1e-3)
    assert learning_rate(cfg, 999) == pytest.approx(2e-5, rel=0.01)


def test_two_process_data_parallel_keeps_replicas_identical(tmp_path):
    # gloo over loopback: the sandbox's hostname may resolve to an address gloo cannot reach
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "--standalone",
        "-m",
        "spk2img",
        "train",
        "--member",
        "tiny",
        "--run-dir",
        str(tmp_path),
        "--steps",
        "3",
        "--patch",
        "16",
        "--batch-size",
        "2",
        "--val-every",
        "100",
        "--val-per-class",
        "1",
        "--no-progress",
    ]
    done = subprocess.run(cmd, env=env, timeout=300, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    (rec,) = _records(tmp_path, "replicas")
    assert rec["world_size"] == 2
    assert rec["max_abs_diff"] == 0.0
    # the replicas trained on different data: the weights moved from their initial values
    assert load_checkpoint(tmp_path / "last.pt")["step"] == 3


def test_train_help_gives_every_flag_its_default_and_a_run_ends_with_a_summary(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "(choices: paper, medium, small, lite, cpu, tiny; default: tiny)" in help_text
    assert "(choices: l1, psnr; default: l1)" in help_text and "(default: 20000)" in help_text
    run = tmp_path / "run"
    flags = "--member tiny --steps 2 --patch 16 --batch-size 2 --val-every 2 --val-per-class 1"
    assert main(["train", *flags.split(), "--workers", "0", "--run-dir", str(run)]) == 0
    err = capsys.readouterr().err
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    (summary,) = [r for r in records if r["kind"] == "summary"]
    assert summary["best_checkpoint"] == str(run / "best.pt") and (run / "best.pt").is_file()
    assert summary["val_set"] == "procedural"
    assert summary["best_psnr"] == summary["last_validation"]["psnr"]
    assert f"best checkpoint {run / 'best.pt'} (procedural validation, " in err
    assert f"{summary['best_psnr']:.2f} dB" in err


def test_the_display_share_sets_how_many_natural_samples_take_the_value_as_the_light(tmp_path):
    """``display_share`` 0: every photo or clip read linear; 1: every one display-referred;
    0.5 about half (a share outside [0, 1] is refused). A display-referred photo is the linear
    one with the gamma not undone."""
    for share, expected in ((0.0, 0.0), (1.0, 1.0), (0.5, 0.5)):
        maker = SampleMaker(16, seed=0, display_share=share)
        rngs = (np.random.default_rng([5, k]) for k in range(400))
        display = np.mean([maker.draw_light(rng) == "display" for rng in rngs])
        assert display == pytest.approx(expected, abs=0.08)
    with pytest.raises(ValueError, match="display-share"):
        TrainConfig(display_share=2)
    assert main(["train", "--display-share", "1.1", "--steps", "1"]) == 2
    grey = (np.arange(48 * 64) % 256).astype(np.uint8).reshape(48, 64)
    Image.fromarray(grey).save(tmp_path / "ramp.png")
    display = load_photo(tmp_path / "ramp.png", "display")
    assert np.allclose(display**2.2, load_photo(tmp_path / "ramp.png"), atol=1e-6)


def test_a_stop_request_takes_the_first_signal_and_a_later_second_stops_at_once():
    previous = signal.getsignal(signal.SIGTERM)
    with StopRequest(again_after_s=0.2) as stop:
        assert not stop.agreed(1) and stop.name == "another process of the run"
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.agreed(1) and stop.signal == signal.SIGTERM and stop.name == "SIGTERM"
        os.kill(os.getpid(), signal.SIGTERM)  # as timeout repeats it: the same request
        assert stop.signal == signal.SIGTERM
        time.sleep(0.2)
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGTERM) is previous


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_ctrl_c_stops_a_run_after_its_step_and_saves_it(tmp_path, stop):
    """Ctrl-C or ``timeout``'s SIGTERM (to the whole process group, as both send it) ends a run
    with a data worker at the step it reached with that step in ``last.pt``, between the
    checkpoints it would have written; the same command continues from there (checked after
    SIGTERM)."""
    run = tmp_path / "run"
    flags = "--member tiny --patch 16 --batch-size 2 --val-per-class 1 --log-every 1"
    cmd = [sys.executable, "-m", "spk2img", "train", *flags.split(), "--run-dir", str(run)]
    long = ["--steps", "100000", "--val-every", "100000", "--checkpoint-every", "100000"]
    proc = subprocess.Popen(
        [*cmd, *long, "--workers", "1", "--no-progress"],
        start_new_session=True,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            if (run / "metrics.jsonl").is_file() and len(_records(run, "train")) >= 3:
                break
            time.sleep(0.2)
        os.killpg(proc.pid, stop)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + stop, err[-2000:]
    (stopped,) = _records(run, "stopped")
    step = stopped["step"]
    assert stopped["signal"] == stop.name and 3 <= step < 100000
    assert load_checkpoint(run / "last.pt")["step"] == step
    assert _records(run, "train")[-1]["step"] == step and not _records(run, "summary")
    assert f"stopped at step {step} of 100000 ({stop.name})" in err and "Traceback" not in err
    if stop == signal.SIGINT:
        return  # the signals stop the run alike: one resume is enough
    more = ["--steps", str(step + 2), "--val-every", "100000", "--workers", "0"]
    assert subprocess.run([*cmd, *more, "--no-progress"], timeout=240).returncode == 0
    assert [r["step"] for r in _records(run, "run")] == [0, step]
    assert [r["step"] for r in _records(run, "train")][-3:] == [step, step + 1, step + 2]


def test_bf16_autocast_on_the_cpu_follows_the_fp32_gradient():
    """``--precision bf16`` on the CPU trains in bf16 convolutions: on the same batch its loss
    is within 0.02 dB of fp32's and its gradient within 5 % (direction within 0.999), so the
    steps go where fp32's go (a tiny member with random weights, PSNR loss)."""
    torch.manual_seed(0)
    model = Spk2ImgNet(get_config("tiny"))
    spikes, truth = (torch.from_numpy(a) for a in SampleMaker(16, seed=5).batch(0, 2))

    def loss_and_gradient(bf16: bool):
        model.zero_grad()
        with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            image, estimates = model(spikes.contiguous(memory_format=torch.channels_last))
            loss = hierarchical_loss(image.float(), estimates.float(), truth, "psnr")
        loss.backward()
        return loss.item(), torch.cat([p.grad.flatten() for p in model.parameters()])

    (loss32, grad32), (loss16, grad16) = loss_and_gradient(False), loss_and_gradient(True)
    assert loss16 == pytest.approx(loss32, abs=0.02)
    assert (grad16 - grad32).norm() < 0.05 * grad32.norm()
    assert torch.nn.functional.cosine_similarity(grad16, grad32, dim=0) > 0.999


def test_a_bf16_run_on_the_cpu_says_so_and_keeps_fp32_weights(tmp_path, capsys):
    run = tmp_path / "run"
    train(TrainConfig(run_dir=str(run), steps=2, precision="bf16", **TINY_RUN))
    (record,) = _records(run, "run")
    assert record["hardware"].endswith("torch thread(s), bf16 autocast")
    state = load_checkpoint(run / "last.pt")
    assert {t.dtype for t in state["model"].values() if t.is_floating_point()} == {torch.float32}
    assert all(np.isfinite(r["loss"]) for r in _records(run, "train"))
    assert main(["train", "--run-dir", str(tmp_path / "x"), "--precision", "fp16"]) == 2
    assert "--precision fp16: choose one of auto, fp32, bf16" in capsys.readouterr().err
