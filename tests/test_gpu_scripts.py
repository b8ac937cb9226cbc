"""The scripts a lent GPU runs, checked on the CPU at small sizes (they name their device)."""

import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_torch_inference_speed_times_each_precision_and_batch_and_its_error(tmp_path):
    """``tiny`` at 24x32 on the CPU: a row per precision and batch, fp32 the reference (its
    batch rows agree to float rounding), bf16 and fp16 within 0.05 of it."""
    script = load_script("torch_inference_speed")
    out = tmp_path / "torch.json"
    argv = ["--device", "cpu", "--size", "24x32", "--batches", "1,2", "--models", "tiny"]
    result = script.main([*argv, "--repeats", "1", "--json", str(out)])
    assert json.loads(out.read_text()) == result and result["device"] == "cpu"
    rows = result["models"]["tiny"]
    assert [(r["precision"], r["batch"]) for r in rows] == [
        (p, b) for p in ("fp32", "bf16", "fp16") for b in (1, 2)
    ]
    assert all(r["ms_per_frame"] > 0 for r in rows)
    for row in rows:
        limit = 1e-5 if row["precision"] == "fp32" else 0.05
        assert row["max_abs_vs_fp32"] <= limit, row
    with pytest.raises(SystemExit):
        script.main(["--device", "cpu", "--precisions", "bf16"])


def test_a_gpu_session_trains_in_the_background_and_brings_the_run_back(tmp_path):
    """``gpu_session.sh train-start`` returns while the run trains on (on the CPU here: the last
    ``--device`` wins); ``train-stop`` stops it at a step it saves and brings its log, metrics
    and state into ``$OUT``."""
    env = {
        **os.environ,
        "OUT": str(tmp_path / "out"),
        "SPK2IMG_RUNS": str(tmp_path / "runs"),
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",  # its python3
    }
    flags = "--member tiny --patch 16 --batch-size 2 --val-per-class 1 --log-every 1 --workers 0"
    long = "--steps 100000 --val-every 100000 --checkpoint-every 100000 --device cpu"

    def session(*args: str) -> str:
        cmd = ["bash", str(ROOT / "scripts" / "gpu_session.sh"), *args]
        done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=180)
        assert done.returncode == 0, done.stderr
        return done.stdout

    assert "in the background" in session("train-start", "t", "300", *flags.split(), *long.split())
    metrics = tmp_path / "runs" / "t" / "metrics.jsonl"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (
            not metrics.is_file() or metrics.read_text().count('"kind": "train"') < 2
        ):
            time.sleep(0.2)
        said = session("train-stop", "t")
    finally:  # never leave the background run behind a failure
        subprocess.run(["pkill", "-KILL", "-f", f"--run-dir {tmp_path / 'runs' / 't'}"])
    brought = tmp_path / "out" / "t"
    records = [json.loads(line) for line in (brought / "metrics.jsonl").read_text().splitlines()]
    (stopped,) = [r for r in records if r["kind"] == "stopped"]
    assert stopped["signal"] == "SIGINT" and stopped["step"] >= 2
    assert torch.load(brought / "last.pt", weights_only=True)["step"] == stopped["step"]
    assert f"stopped at step {stopped['step']} of 100000" in said
    assert "Traceback" not in (brought / "train.log").read_text()
    assert "not running" in session("train-stop", "t")
