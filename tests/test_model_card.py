"""The model card (spk2img.training.model_card) of a named model: its header, how to run it,
the sensors it was trained on and the run's figures come from the checkpoint and the log."""

import json
import shutil

from spk2img.model.checkpoint import average_checkpoints
from spk2img.training.model_card import render
from spk2img.training.train import TrainConfig, train

SCORES = {"psnr": 30.0, "ssim": 0.9, "psnr_fast": 25.0}
RESULTS = {"procedural": {"network": SCORES, "tfp_best": SCORES, "tfi": SCORES}}


def _two_step_run(tmp_path, standin_model, **flags):
    """A 2-step `tiny` run's folder (more ``TrainConfig`` ``flags`` if given) and a stand-in
    graph named as the shipped `real`."""
    run = tmp_path / "run"
    config = dict(member="tiny", patch=16, batch_size=2, val_every=2, val_per_class=1)
    fast = dict(log_every=1, progress=False, warmup_steps=1, workers=0)
    train(TrainConfig(steps=2, run_dir=str(run), **config, **fast, **flags))
    onnx = tmp_path / "spk2img-real.onnx"
    shutil.copy(standin_model, onnx)
    return run, onnx


def test_card_names_the_model_its_sensors_and_its_run(tmp_path, standin_model):
    run, onnx = _two_step_run(tmp_path, standin_model)
    results = RESULTS
    card = render(run / "last.pt", onnx, run, results, history="two steps")
    assert card.startswith("# Model card: spk2img `real` model")
    assert "`spk2img reconstruct --model real`" in card and "spk2img-real.encoder.onnx" in card
    assert "**random (procedural scenes only)**" in card
    assert "steps: **2** of 2 planned" in card and "- history: two steps" in card
    assert "| 2 | 0.00 |" in card  # the validation at step 2, from the run's log
    assert "| Spk2ImgNet tiny (ONNX) | 30.00 | 0.900 | 25.00 |" in card
    assert f"cp {run}/last.pt runs/run/" in card  # the run's state is there: how to continue
    (run / "last.pt").unlink()
    card = render(run / "best.pt", onnx, run, results, history="")
    assert "resumable state is not kept" in card
    assert "- weights:" not in card


def test_card_of_averaged_weights_names_what_they_average(tmp_path, standin_model):
    """Weights averaged from checkpoints (scripts/average_checkpoints.py) say so on the card,
    and what the mean was chosen on when that was recorded (``--chosen-on``)."""
    run, onnx = _two_step_run(tmp_path, standin_model)
    average_checkpoints([run / "best.pt", run / "last.pt"], [0.25, 0.75], run / "soup.pt")
    results = {**RESULTS, "natural": RESULTS["procedural"]}
    card = render(run / "soup.pt", onnx, run, results, history="")
    assert "- weights: the weighted mean of 0.25 x `best.pt` (step 2), 0.75 x `last.pt`" in card
    assert "(the mean PSNR of both regimes)" in card  # last.pt records none: the default
    chosen = "real video frames"
    average_checkpoints([run / "best.pt", run / "last.pt"], [0.5, 0.5], run / "soup.pt", chosen)
    card = render(run / "soup.pt", onnx, run, results, history="")
    assert "(the real-video validation's PSNR on whole frames (docs/real_video.md))" in card


def test_card_names_every_hardware_that_trained_the_checkpoint(tmp_path, standin_model):
    """A run resumed on other machines: the card lists those that trained up to the
    checkpoint's step (the log's run records before it), not the last one alone."""
    run, onnx = _two_step_run(tmp_path, standin_model)
    log = run / "metrics.jsonl"
    records = [json.loads(line) for line in log.read_text().splitlines()]
    (start,) = [r for r in records if r["kind"] == "run"]
    start["hardware"] = "machine A"
    records += [
        {"kind": "run", "step": 1, "hardware": "machine B"},
        {"kind": "run", "step": 1, "hardware": "machine A"},
        {"kind": "run", "step": 2, "hardware": "machine C"},  # after the checkpoint's step 2
    ]
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    card = render(run / "last.pt", onnx, run, RESULTS, history="")
    assert "optimiser steps on machine A; then machine B." in card
    assert "machine C" not in card


def test_card_of_a_run_with_a_weight_average_says_so(tmp_path, standin_model):
    """A run with ``--ema-decay`` ships its average (``best.pt``), or its trained weights
    (``last.pt``): the card's command and weights say which."""
    run, onnx = _two_step_run(tmp_path, standin_model, ema_decay=0.99)
    card = render(run / "best.pt", onnx, run, RESULTS, history="")
    assert " --ema-decay 0.99`" in card
    assert "- weights: the moving average of the trained weights, 0.99 of it kept" in card
    trained = render(run / "last.pt", onnx, run, RESULTS, history="")  # the trained weights
    assert "- weights: the trained weights of this step, not the run's moving average" in trained
