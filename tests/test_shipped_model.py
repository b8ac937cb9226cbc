"""The shipped default model end to end: its ONNX graph verifies against its checkpoint, the
README's main command runs on the shipped sample stream, and the ONNX backend, the torch
backend and the HTTP service give the same frames."""

import json
from pathlib import Path

import numpy as np
from service_support import run_server

from spk2img.cli import main
from spk2img.export import hard_cases
from spk2img.export.metadata import weights_sha256
from spk2img.export.verify import verify_onnx
from spk2img.model.checkpoint import load_checkpoint, load_model
from spk2img.runtime.onnx_backend import (
    OnnxModel,
    default_model_path,
    graph_metadata,
    shipped_models,
)
from spk2img.runtime.torch_backend import DEFAULT_CHECKPOINT

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fast_motion_250x400.dat"
CENTERS = "20,97"


def test_shipped_onnx_is_the_shipped_checkpoint_and_verifies():
    """The shipped default graph holds its checkpoint's weights and matches it on the hard
    content cases and an odd size (the CLI's ``verify --quick`` runs on tiny in test_export)."""
    meta = OnnxModel(threads=1).metadata
    assert meta["weights_sha256"] == weights_sha256(load_checkpoint(DEFAULT_CHECKPOINT)["model"])
    assert json.loads(meta["window"]) == 41 and float(meta["rate"]) == 0.6
    cases = hard_cases.content_cases() + hard_cases.size_cases(((17, 23),), threads=(1,))
    report = verify_onnx(default_model_path(), load_model(DEFAULT_CHECKPOINT), cases)
    assert report.passed and len(report.results) == 7, report.table()


def test_every_shipped_model_is_its_checkpoint_with_its_block_graphs():
    """Each ``spk2img-<name>.onnx`` (the names ``--model`` takes), its encoder and head graphs
    and the ``.pt`` beside it hold the same weights, and its card exists."""
    assert {"default", "real"} <= set(shipped_models())
    docs = Path(__file__).resolve().parents[1] / "docs"
    for name, path in shipped_models().items():
        weights = weights_sha256(load_checkpoint(path.with_suffix(".pt"))["model"])
        for graph in (path, path.with_suffix(".encoder.onnx"), path.with_suffix(".head.onnx")):
            assert graph_metadata(graph)["weights_sha256"] == weights, graph
        assert graph_metadata(path)["name"] == f"spk2img-{name}"
        card = "model_card.md" if name == "default" else f"model_card_{name}.md"
        assert f"spk2img/assets/models/spk2img-{name}.onnx" in (docs / card).read_text()


def test_readme_command_and_backends_and_service_agree(tmp_path):
    """README's command (every 7th centre, each block encoded once) on the sample stream; the
    torch backend and the service, on whole windows at two of its centres, give its frames."""
    png_dir, readme_out = tmp_path / "png", tmp_path / "r.npz"
    readme = ["reconstruct", str(SAMPLE), "--out", str(readme_out), "--png-dir", str(png_dir)]
    assert main([*readme, "--stride", "7", "--no-progress"]) == 0
    ran = np.load(readme_out)
    assert ran["centers"].tolist() == list(range(20, 98, 7))
    assert len(list(png_dir.glob("*.png"))) == 12
    frames = ran["frames"][[0, -1]]  # centres 20 and 97
    assert frames.shape == (2, 250, 400) and np.isfinite(frames).all()
    outs = {"torch": tmp_path / "torch.npz", "remote": tmp_path / "remote.npz"}
    args = ["reconstruct", str(SAMPLE), "--out", str(outs["torch"]), "--centers", CENTERS]
    assert main([*args, "--no-progress", "--backend", "torch"]) == 0
    with run_server(default_model_path(), "--threads", "2") as server:
        args = ["reconstruct", str(SAMPLE), "--out", str(outs["remote"]), "--centers", CENTERS]
        assert main([*args, "--url", server.url, "--no-progress"]) == 0
    np.testing.assert_allclose(np.load(outs["torch"])["frames"], frames, atol=1e-4)
    np.testing.assert_allclose(np.load(outs["remote"])["frames"], frames, atol=1e-5)
