"""The GPU rows of the benchmark and the fp16 graphs (docs/gpu.md), checked on any machine:
where no GPU runs, every GPU row is written as not yet measured, never with a figure; the GPU
job's code runs here on the CPU provider; fp16 block graphs load and stay close to fp32."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from unittest import mock

import numpy as np
import pytest

from spk2img.bench import artifacts, gpu
from spk2img.bench.report import gpu_table, markdown
from spk2img.bench.worker import measure_gpu
from spk2img.cli import main
from spk2img.export.quantize import graph_io, reduce_block_graphs, reduce_precision
from spk2img.export.verify import case_passes
from spk2img.runtime.block_codec import OnnxBlockCodec
from spk2img.runtime.onnx_backend import OnnxModel, available_providers, default_model_path

HAS_CUDA = "CUDAExecutionProvider" in available_providers()


def test_without_a_gpu_every_row_is_not_yet_measured():
    legacy = json.loads(open("docs/bench.json").read())  # a run from before the GPU rows
    legacy.pop("gpu", None)
    table = gpu_table(legacy)
    rows = [line for line in table.splitlines() if line.startswith("| Spk2ImgNet")]
    assert len(rows) == len(gpu.planned_rows()) + len(gpu.SERVICE_CLIENTS)  # and the service
    assert all(gpu.NO_GPU in row and "none (no GPU)" in row for row in rows)
    assert not any(char.isdigit() for row in rows for char in row.split("|")[5])
    assert "## On a GPU" in markdown(legacy)


def test_measured_rows_name_the_gpu():
    section = {
        "device": "cuda",
        "gpu": "Some GPU",
        "error": None,
        "rows": [{**row, "ms_per_frame": 12.5, "error": None} for row in gpu.planned_rows()],
        "service": {
            "provider": "CUDAExecutionProvider",
            "levels": [
                {"clients": n, "service": {"frames_per_s": 9.0 * n}} for n in gpu.SERVICE_CLIENTS
            ],
        },
    }
    table = gpu_table(
        {"command": "spk2img bench", "settings": {"height": 8, "width": 8}, "gpu": section}
    )
    rows = [line for line in table.splitlines() if line.startswith("| Spk2ImgNet")]
    assert all("Some GPU (cuda)" in row for row in rows) and gpu.NO_GPU not in table
    assert "| 12.5 | 80.0 |" in rows[0] and "9.00" in rows[-2] and "36.00" in rows[-1]
    assert "service over HTTP, 1 client |" in rows[-2] and "4 clients" in rows[-1]
    assert [r.split("|")[1].strip() for r in rows[:1] + rows[-3:-2]] == [
        "Spk2ImgNet shipped",
        "Spk2ImgNet paper (untrained)",
    ]


def test_a_gpu_only_run_keeps_the_rows_it_measured_when_cut_short(tmp_path, monkeypatch):
    """Every shipped architecture and batch 1, 8 and 32 are planned; bench.json is rewritten
    after each row, so a run stopped by a time limit keeps what it measured."""
    planned = gpu.planned_rows()
    assert {r["weights"] for r in planned} == {"shipped", "tiny", "cpu", "paper"}
    assert {r["batch"] for r in planned} == {0, 1, 8, 32}
    shutil.copy("docs/bench.json", tmp_path / "bench.json")
    done = []

    def fake_job(spec, timeout):
        if len(done) == 5:
            raise SystemExit("the session's time limit")
        done.append(spec)
        return {"device": "cuda", "provider": "CUDAExecutionProvider", "ms_per_frame": 2.0}

    def no_conversion(source, target, precision):
        shutil.copy(source, target)

    monkeypatch.setattr(gpu, "gpu_device", lambda requested, model: ("cuda", ""))
    monkeypatch.setattr(gpu, "run_job", fake_job)
    monkeypatch.setattr("spk2img.export.quantize.reduce_precision", no_conversion)
    monkeypatch.setattr("spk2img.export.quantize.reduce_block_graphs", lambda *a: None)
    monkeypatch.setattr(artifacts, "make_graph", mock.Mock(side_effect=RuntimeError("skip")))
    args = ["bench", "--quick", "--gpu-only", "--skip-service", "--out-dir", str(tmp_path)]
    with pytest.raises(SystemExit):
        main(args)
    rows = json.loads((tmp_path / "bench.json").read_text())["gpu"]["rows"]
    assert [(r["weights"], r["precision"], r["batch"]) for r in rows] == [
        (r["weights"], r["precision"], r["batch"]) for r in planned[:5]
    ]
    assert all(r["ms_per_frame"] == 2.0 for r in rows)
    assert [Path(s["model"]).name for s in done] == ["spk2img-default.onnx"] * 5
    assert (tmp_path / "bench.md").read_text().count("| 2.00 | 500 |") == 5


@pytest.mark.skipif(HAS_CUDA, reason="a CUDA provider is here: auto would measure")
def test_auto_finds_no_gpu_here_and_says_why():
    device, why = gpu.gpu_device("auto", default_model_path())
    assert device is None and why.startswith(gpu.NO_GPU)
    assert gpu.gpu_device("cpu", default_model_path()) == (None, "not measured (--device cpu)")


def test_bench_device_and_gpu_only_errors(tmp_path, capsys):
    assert main(["bench", "--gpu-only"]) == 2
    assert main(["bench", "--gpu-only", "--out-dir", str(tmp_path)]) == 2
    assert "no bench.json" in capsys.readouterr().err
    if not HAS_CUDA:
        assert main(["bench", "--quick", "--device", "cuda", "--out-dir", str(tmp_path)]) == 2
        assert "CUDAExecutionProvider" in capsys.readouterr().err


def test_the_gpu_job_runs_on_the_cpu_provider(tmp_path):
    rng = np.random.default_rng(3)
    cases = tmp_path / "cases"
    cases.mkdir()
    np.save(cases / "spikes.npy", (rng.random((2, 41, 16, 24)) < 0.3).astype(np.uint8))
    np.save(tmp_path / "stream.npy", (rng.random((60, 16, 24)) < 0.3).astype(np.uint8))
    spec = {
        "model": str(default_model_path()),
        "device": "cpu",
        "threads": [1],
        "repeats": 1,
        "cases": str(cases),
        "spikes": str(tmp_path / "stream.npy"),
    }
    for batch, self_ensemble in ((3, False), (1, True), (0, False)):
        result = measure_gpu({**spec, "batch": batch, "self_ensemble": self_ensemble})
        assert result["provider"] == "CPUExecutionProvider" and result["ms_per_frame"] > 0


def test_fp16_graphs_keep_their_io_and_stay_close(tmp_path):
    out = tmp_path / "m16.onnx"
    reduce_precision(default_model_path(), out, "fp16")
    encoder, head = reduce_block_graphs(default_model_path(), out, "fp16")
    import onnx

    for path, source in ((encoder, ".encoder.onnx"), (head, ".head.onnx")):
        original = default_model_path().with_suffix(source)
        assert graph_io(onnx.load(path)) == graph_io(onnx.load(original))
    codec, reference = OnnxBlockCodec(out, 1), OnnxBlockCodec(None, 1)
    assert codec.metadata["precision"] == "fp16"
    block = (np.random.default_rng(4).random((13, 16, 24)) < 0.3).astype(np.float32)
    images = [c.head([c.encode(block)] * 5, 16, 24) for c in (codec, reference)]
    assert np.abs(images[0] - images[1]).max() < 1e-2
    window = (np.random.default_rng(5).random((1, 41, 16, 24)) < 0.3).astype(np.float32)
    assert np.abs(OnnxModel(out, 1)(window) - OnnxModel(None, 1)(window)).max() < 1e-2


def test_reduced_precision_cases_pass_on_psnr_not_atol():
    close = {"max_abs": 1e-3, "psnr_db": 60.0, "nonfinite": 0}
    assert not case_passes(close, "fp32", 1e-4) and case_passes(close, "fp16", 1e-4)
    assert not case_passes({**close, "psnr_db": 25.0}, "fp16", 1e-4)
    assert not case_passes({**close, "nonfinite": 1}, "fp16", 1.0)
    assert case_passes({**close, "max_abs": 1e-5}, "fp32", 1e-4)
    numpy_scores = {"max_abs": np.float32(1e-3), "psnr_db": np.float64(60.0), "nonfinite": 0}
    assert json.dumps([case_passes(numpy_scores, p, 1e-4) for p in ("fp32", "fp16")])


def test_a_graph_that_cannot_be_made_fails_its_rows_not_the_run(tmp_path):
    """The paper member's export, or an fp16 conversion without block graphs beside the fp32
    graph (what stopped the whole GPU section before any row), costs only its own rows."""
    lonely = tmp_path / "lonely.onnx"
    shutil.copy(default_model_path(), lonely)  # no encoder and head beside it
    messages = []

    def broken():
        raise RuntimeError("export failed")

    graph = gpu.row_graphs({"broken": broken, "lonely": lambda: lonely}, tmp_path, messages.append)
    assert graph("broken", "fp32") is None and graph("broken", "fp16") is None
    assert graph("lonely", "fp32") == lonely and graph("lonely", "fp16") is None
    assert len(messages) == 2 and "export failed" in messages[0]
    assert "fp16 graph of lonely" in messages[1]
    row = {"weights": "broken", "precision": "fp32", "mode": "one-shot", "batch": 1}
    assert gpu.measured_row(row, None, {}, messages.append)["error"] == "no broken graph to run"
