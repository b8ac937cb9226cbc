"""The scripts a lent GPU runs, checked on the CPU at small sizes (they name their device)."""

import importlib.util
import json
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from spk2img.cli import main

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
    table = load_script("gpu_results").inference_table(result).splitlines()
    assert table[0] == "# Torch inference on cpu" and len(table) == 6 + len(rows)
    assert table[-1].startswith("| tiny | fp16 | 2 | ") and table[6].endswith("| — |")


def test_a_gpu_session_trains_its_runs_then_resumes_them_and_brings_them_back(tmp_path):
    """``gpu_session.sh session`` (on the CPU here: the last ``--device`` wins) unpacks the
    one-part training pack, trains the listed runs for the seconds given, stops them at a step
    they save and brings back their logs, metrics and checkpoints, under 8 files; a run
    started in the background with ``train-start`` (here: the same run, resumed) returns at
    once, and ``train-stop`` stops it with Ctrl-C and brings it back too."""
    data = tmp_path / "collection"  # any name: the session reads it from PACK.json
    (data / "photos").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("leaf", "rock", "wall"):
        Image.fromarray(rng.integers(0, 256, (40, 48), np.uint8)).save(
            data / "photos" / f"{name}.png"
        )
    held_out = data / "video2" / "vid4_walk"  # a real-video clip: filmed into windows, not packed
    held_out.mkdir(parents=True)
    for k in range(4):
        frame = np.roll(rng.integers(0, 256, (40, 48), np.uint8), k, axis=1)
        Image.fromarray(frame).save(held_out / f"{k:05d}.png")
    pack = tmp_path / "pack"
    assert main(["pack-data", "--data", str(data), "--out", str(pack), "--max-mib", "1"]) == 0
    flags = "--member tiny --patch 16 --batch-size 2 --val-per-class 1 --log-every 1 --workers 0"
    flags += " --steps 100000 --val-every 100000 --checkpoint-every 100000 --device cpu"
    (tmp_path / "runs.txt").write_text(f"# the run of this test\nt {flags}\n")
    env = {
        **os.environ,
        "OUT": str(tmp_path / "out"),
        "SPK2IMG_RUNS": str(tmp_path / "runs"),
        "SPK2IMG_DATA": str(tmp_path / "data"),
        "SPK2IMG_PACK": str(pack),
        "SPK2IMG_SESSION_RUNS": str(tmp_path / "runs.txt"),
        "SPK2IMG_SESSION_MEASURE": "0",
        "PARTS_STORE": str(tmp_path / "parts"),
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",  # its python3
    }

    def session(*args: str) -> str:
        cmd = ["bash", str(ROOT / "scripts" / "gpu_session.sh"), *args]
        done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=180)
        assert done.returncode == 0, done.stderr
        return done.stdout

    def brought() -> list[dict]:
        with tarfile.open(tmp_path / "out" / "report.tar.gz") as report:
            names = report.getnames()
            assert "report/environment.txt" in names and "report/t/train.log" in names
            lines = report.extractfile("report/t/metrics.jsonl").read().decode().splitlines()
        return [json.loads(line) for line in lines]

    said = session("session", "8")
    records = brought()
    (logged,) = [r for r in records if r["kind"] == "data"]
    assert logged["real_video_windows"] == 2  # the clip's two speed bins, from the pack's file
    (stopped,) = [r for r in records if r["kind"] == "stopped"]
    assert stopped["signal"] == "SIGINT" and stopped["step"] >= 1
    assert f"stopped at step {stopped['step']} of 100000" in said
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["report.tar.gz", "t-last.pt"]
    last = torch.load(tmp_path / "out" / "t-last.pt", weights_only=True)
    assert last["step"] == stopped["step"]
    results, state = load_script("gpu_results"), tmp_path / "state"
    for older in ("a", "b"):  # two runs' states there already: one must go
        (state / older).mkdir(parents=True)
        (state / older / "last.pt").write_bytes(b"")
    said = results.take_results(tmp_path / "out", state, tmp_path / "back", tmp_path / "docs")
    assert said[0].startswith(f"t: step {stopped['step']}, ") and "fp16 weights" in said[0]
    assert "no torch inference rows came back" in said
    assert f"more than two states in {state}: drop the last.pt of a, b" in said
    assert (state / "t" / "metrics.jsonl").read_text().count('"kind": "stopped"') == 1
    kept = torch.load(state / "t" / "last.pt", weights_only=True)
    assert kept["step"] == stopped["step"] and "optimizer" not in kept
    assert {t.dtype for t in kept["model"].values() if t.is_floating_point()} == {torch.float16}
    assert (tmp_path / "docs" / "gpu_environment.txt").read_text().startswith("Python 3.")

    try:
        args = [
            "train-start",
            "t",
            "300",
            *flags.split(),
            "--data",
            str(tmp_path / "data/collection"),
        ]
        assert "in the background" in session(*args)
        metrics = tmp_path / "runs" / "t" / "metrics.jsonl"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and metrics.read_text().count('"kind": "train"') < (
            sum(r["kind"] == "train" for r in records) + 2
        ):
            time.sleep(0.2)
        said = session("train-stop", "t")
    finally:  # never leave the background run behind a failure
        subprocess.run(["pkill", "-KILL", "-f", f"--run-dir {tmp_path / 'runs' / 't'}"])
    resumed = json.loads(metrics.read_text().splitlines()[-1])
    assert resumed["kind"] == "stopped" and resumed["step"] > stopped["step"]
    assert torch.load(tmp_path / "out" / "t-last.pt", weights_only=True)["step"] == resumed["step"]
    assert "Traceback" not in (tmp_path / "out" / "report" / "t" / "train.log").read_text()
    assert "not running" in session("train-stop", "t")
