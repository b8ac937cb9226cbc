"""``spk2img bench --quick``: every expected row and column is there and every number is finite
(no test asserts a time); and the pieces the benchmark relies on."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from spk2img.bench.cases import SCENE_CLASSES, benchmark_set
from spk2img.bench.natural import natural_set
from spk2img.bench.profile import summarise, top_operators
from spk2img.bench.rows import NetRow, TfiRow, TfpRow, row_from_json, row_to_json
from spk2img.bench.runner import QUICK
from spk2img.bench.scores import best_tfp_window, quality
from spk2img.bench.worker import peak_rss_mib
from spk2img.cli import main
from spk2img.evaluation.metrics import psnr
from spk2img.evaluation.scoring import TFP_WINDOWS, score_images
from spk2img.runtime.classical import tfp
from spk2img.sim.simulator import CENTER_FRAME


@pytest.fixture(scope="module")
def held_out_dir(tmp_path_factory) -> Path:
    """A data folder with one of the natural validation's held-out photos (a random texture)
    and a photo that is not held out."""
    root = tmp_path_factory.mktemp("data")
    rng = np.random.default_rng(5)
    for name in ("kodak24_kodim08.png", "not_held_out.png"):
        grey = rng.integers(0, 256, (24, 32), dtype=np.uint8).repeat(4, 0).repeat(4, 1)
        Image.fromarray(grey).save(root / name)
    return root


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory, held_out_dir):
    out = tmp_path_factory.mktemp("bench")
    args = ["bench", "--quick", "--out-dir", str(out), "--data", str(held_out_dir)]
    assert main([*args, "--stream-models", "cpu,tiny"]) == 0
    return out, json.loads((out / "bench.json").read_text()), (out / "bench.md").read_text()


def _finite(*values) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


@pytest.mark.slow
def test_quick_run_has_every_row_and_finite_numbers(quick_run):
    out, results, _ = quick_run
    rows = {(r["label"], r["backend"]): r for r in results["rows"]}
    assert ("TFI", "numpy") in rows
    assert any(label.startswith("TFP-41") for label, _ in rows)
    assert any("best single window" in label for label, _ in rows)
    tiny = {r["backend"]: r for r in results["rows"] if r["weights"] == "tiny"}
    assert set(tiny) == set(QUICK.member_backends)
    for row in results["rows"]:
        if row["kind"] != "net" or row["backend"] in ("torch", "onnx"):
            assert row["error"] is None, row
        if row["error"] is not None:
            assert row["error"], row  # a failed variant says why
            continue
        assert _finite(row["peak_rss_mib"], *row["ms_per_frame"].values())
        assert set(row["ms_per_frame"]) == {"1", "2"}
        if row["kind"] == "net":
            assert _finite(row["params"], row["macs"]["reference"], row["max_abs_error"])
        if row["scored"]:
            q = row["quality"]
            assert _finite(q["psnr"], q["ssim"])
            assert set(q["classes"]) == set(SCENE_CLASSES)
        else:
            assert "quality" not in row  # untrained: timed, never scored
    shipped = {r["backend"]: r for r in results["rows"] if r["weights"] == "shipped"}
    assert set(shipped) == set(QUICK.trained_backends)
    assert tiny["torch"]["max_abs_error"] == shipped["torch"]["max_abs_error"] == 0
    assert shipped["onnx"]["max_abs_error"] < 1e-3  # the shipped graph against its checkpoint
    assert shipped["onnx-fp16"]["max_abs_error"] < 0.05
    # the self-ensemble moves the image (the mean of four mirrored views), by a fraction
    assert 1e-4 < shipped["onnx-ensemble"]["max_abs_error"] < 0.5
    assert shipped["onnx-ensemble"]["macs"] == {
        size: 4 * macs for size, macs in shipped["onnx"]["macs"].items()
    }
    assert _finite(*results["matmul_gflops"].values())
    levels = results["service"]["levels"]
    assert [level["clients"] for level in levels] == [1, 4]
    for level in levels:
        for side in ("service", "in_process"):
            assert _finite(level[side]["frames_per_s"], level[side]["p99_ms"])
        assert _finite(level["overhead"])
    assert (out / "images" / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_quick_natural_validation(quick_run, held_out_dir):
    """With --data, every scored row is scored on the held-out sources per sensor regime, with
    the figures of training's scoring of the same images; untrained rows are not."""
    out, results, text = quick_run
    natural = results["natural"]
    assert natural["sources"] == ["kodak24_kodim08.png"]  # the one held-out source only
    assert natural["count"] == 6 and natural["regimes"] == ["ideal", "fitted"]
    assert (natural["height"], natural["width"]) == QUICK.natural_size
    scenes = natural_set([held_out_dir], *QUICK.natural_size).scenes
    tfp41 = next(r for r in results["rows"] if r["label"].startswith("TFP-41"))
    expected = score_images([tfp(s.spikes, [CENTER_FRAME], 41)[0] for s in scenes], scenes)
    assert tfp41["natural"] == pytest.approx(expected)
    for row in results["rows"]:
        if row["error"] is None and row["scored"]:
            q = row["natural"]
            assert _finite(q["psnr_ideal"], q["psnr_fitted"], q["ssim_ideal"], q["ssim_fitted"])
        else:
            assert "natural" not in row
    section = text.split("## Natural validation")[1].split("\n## ")[0]
    assert "kodak24_kodim08.png" in section and "| noise-free: PSNR / SSIM |" in section
    assert f"| {tfp41['label']} | numpy |" in section and "nan" not in section


def test_data_without_held_out_sources_exits_2(tmp_path, capsys):
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    assert main(["bench", "--quick", "--out-dir", str(out), "--data", str(data)]) == 2
    assert "none of the held-out sources" in capsys.readouterr().err
    assert not (out / "bench.json").exists()


@pytest.mark.slow
def test_quick_streaming_section(quick_run):
    """Block reuse streams each model asked for with the whole-window frames and fewer encodes;
    every quality tier is timed and scored per scene class."""
    out, results, text = quick_run
    streaming = json.loads((out / "bench_streaming.json").read_text())
    assert streaming["streaming"] == results["streaming"]
    assert [s["model"] for s in results["streaming"]] == ["spk2img-cpu", "spk2img-tiny"]
    rows = []
    for s in results["streaming"]:
        assert s["stride"] == 7 and s["frames"] == 90 and 0 < s["mac_ratio"] < 1
        rows += s["rows"]
    for row in rows:
        whole, reuse = row["whole"], row["reuse"]
        assert (
            whole["reconstructor"] == "NetStream" and reuse["reconstructor"] == "BlockReuseStream"
        )
        assert whole["outputs"] == reuse["outputs"] == (90 - 41) // 7 + 1
        assert reuse["blocks_encoded"] < 5 * reuse["outputs"]
        assert row["max_abs_diff"] <= 1e-5 and _finite(row["ratio"])
    tiers = results["tiers"]["tiers"]
    assert set(tiers) == {"best", "balanced", "fast"}
    for entry in tiers.values():
        assert set(entry["quality"]["classes"]) == set(SCENE_CLASSES)
        assert all(_finite(*per_class.values()) for per_class in entry["ms"].values())
    # fast is TFP-41 and balanced never scores below it: it is TFP-41 or the network per tile
    assert tiers["balanced"]["quality"]["psnr"] >= tiers["fast"]["quality"]["psnr"]
    md = (out / "bench_streaming.md").read_text()
    assert "reuse / whole" in md and "| balanced |" in md and "bench_streaming.md" in text
    assert md.count("| `spk2img-tiny` (`tiny`") == len(results["settings"]["threads"])


def test_stream_models_must_be_installed(tmp_path, capsys):
    """A ``--stream-models`` name that is not a shipped model is a CLI error before any work."""
    code = main(
        ["bench", "--streaming-only", "--stream-models", "tiny,nope", "--out-dir", str(tmp_path)]
    )
    assert code == 2
    assert "no shipped model nope" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_quick_markdown_tables(quick_run):
    _, results, text = quick_run
    assert "`spk2img bench --quick" in text and "Machine:" in text
    for column in (
        "params",
        "G MACs/frame",
        "ms/frame (1 thr)",
        "ms/frame (2 thr)",
        "peak RSS (MiB)",
        "PSNR (dB)",
        "SSIM",
        "max abs err vs torch",
        "GFLOP/s (1 thr)",
        "% of matmul (2 thr)",
        "service frames/s",
        "p99 ms",
        "overhead (x)",
        *SCENE_CLASSES,
        "ideal sensor",
        "real-like sensor",
    ):
        assert f"| {column} |" in text or f" {column} |" in text, column
    table = text.split("## Speed and error")[1].split("##")[0]
    for row in results["rows"]:
        assert f"| {row['label']} | {row['backend']} |" in table
    assert "| untrained | untrained |" in table
    assert "nan" not in table and "inf" not in table


def test_quick_profile_says_where_each_graph_spends_its_time(quick_run):
    """Every fp32 ONNX row is profiled: its call's ms and its kernels by operator type, whose
    sum stays within the call, Conv among them; the report names the top types with shares."""
    _, results, text = quick_run
    onnx_rows = {
        r["label"] for r in results["rows"] if r["kind"] == "net" and r["backend"] == "onnx"
    }
    profiles = results["profiles"]
    assert {p["label"] for p in profiles} == onnx_rows and onnx_rows
    for profile in profiles:
        assert "error" not in profile, profile
        assert 0 < sum(profile["ops"].values()) <= profile["run_ms"] * profile["threads"] + 1
        assert "Conv" in profile["ops"]
    section = text.split("## Where the time goes")[1].split("##")[0]
    for profile in profiles:
        assert f"| {profile['label']} |" in section
    assert re.search(r"Conv \d+ %", section)


def test_summarise_reads_the_last_run_of_a_trace():
    kernel = {"cat": "Node", "ph": "X"}
    events = [
        {"name": "model_run", "ts": 0, "dur": 100},
        {**kernel, "name": "a_kernel_time", "ts": 10, "dur": 50, "args": {"op_name": "Conv"}},
        {"name": "model_run", "ts": 200, "dur": 90},
        {**kernel, "name": "b_kernel_time", "ts": 210, "dur": 30, "args": {"op_name": "Conv"}},
        {**kernel, "name": "c_kernel_time", "ts": 250, "dur": 20, "args": {"op_name": "Relu"}},
        {**kernel, "name": "c_fence_before", "ts": 250, "dur": 5, "args": {"op_name": "Relu"}},
    ]
    assert summarise(events) == {"run_ms": 0.09, "ops": {"Conv": 0.03, "Relu": 0.02}}
    shares = top_operators({"Conv": 6.0, "Relu": 3.0, "Add": 1.0}, count=2)
    assert shares == [("Conv", 0.6), ("Relu", 0.3), ("other", pytest.approx(0.1))]


def test_rows_round_trip_through_json():
    for row in (TfpRow(9, "best"), TfiRow(), NetRow("tiny", "onnx", "/m.onnx", trained=False)):
        assert row_from_json(json.loads(json.dumps(row_to_json(row)))) == row


def test_benchmark_set_is_fixed_and_scores_classical_methods():
    cases = benchmark_set(1, 24, 32)
    again = benchmark_set(1, 24, 32)
    assert np.array_equal(cases.spikes, again.spikes) and cases.classes == list(SCENE_CLASSES)
    assert cases.spikes.shape == (5, 41, 24, 32) and cases.truth.shape == (5, 24, 32)
    assert best_tfp_window(cases) in TFP_WINDOWS
    perfect = quality(cases.truth, cases)
    assert perfect["psnr"] == math.inf and perfect["ssim"] == pytest.approx(1.0)


def test_quality_splits_the_benchmark_set_by_sensor():
    """Per-sensor scores average exactly the windows each sensor filmed: spoiling only the
    real-like windows lowers their score alone."""
    cases = benchmark_set(2, 24, 32)
    assert cases.sensors == ["ideal", "real"] * len(SCENE_CLASSES)
    images = cases.truth.copy()
    images[1::2] = np.clip(images[1::2] + 0.1, 0, 1)  # the real-like windows, 20 dB off at most
    q = quality(images, cases)
    assert set(q["sensors"]) == {"ideal", "real"}
    assert q["sensors"]["ideal"]["psnr"] == math.inf
    spoilt = [psnr(i, t) for i, t in zip(images[1::2], cases.truth[1::2], strict=True)]
    assert q["sensors"]["real"]["psnr"] == pytest.approx(np.mean(spoilt))
    assert 19.9 < q["sensors"]["real"]["psnr"] < 40


@pytest.mark.skipif(sys.platform != "linux", reason="VmHWM is Linux's")
def test_worker_peak_rss_is_its_own():
    """``ru_maxrss`` would include this (parent) process's resident set at the fork."""
    ballast = np.ones(64 * 2**20, np.uint8)  # 64 MiB resident here
    code = "from spk2img.bench.worker import peak_rss_mib; print(peak_rss_mib())"
    child = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert float(child.stdout) < peak_rss_mib() - ballast.nbytes / 2**20 / 2


@pytest.mark.parametrize(
    "flags",
    [
        ["--threads", "0"],
        ["--members", "huge"],
        ["--trained", "nothing"],
        ["--repeats", "0"],
        ["--data", "no/such/folder"],
    ],
)
def test_bad_options_exit_2(tmp_path, flags, capsys):
    assert main(["bench", "--quick", "--out-dir", str(tmp_path), *flags]) == 2
    assert "error" in capsys.readouterr().err
