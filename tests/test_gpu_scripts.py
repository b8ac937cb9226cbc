"""The scripts a lent GPU runs, checked on the CPU at small sizes (they name their device)."""

import importlib.util
import json
from pathlib import Path

import pytest

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
