"""The shipped models: each graph holds its checkpoint's weights; the default verifies against
its checkpoint, the README's main command runs on the shipped sample stream, and the ONNX
backend, the torch backend and the HTTP service give the same frames; the folded ``cpu``
verifies at sizes off its multiple and its block graphs stream like its network."""

import json
import shlex
from pathlib import Path

import numpy as np
from service_support import run_server

from spk2img import read_spikes, write_spikes
from spk2img.cli import main
from spk2img.export import hard_cases
from spk2img.export.block_graphs import block_parity
from spk2img.export.metadata import weights_sha256
from spk2img.export.verify import ATOL, verify_onnx
from spk2img.model.checkpoint import load_checkpoint, load_model
from spk2img.runtime.onnx_backend import (
    OnnxModel,
    default_model_path,
    graph_metadata,
    shipped_models,
)
from spk2img.runtime.torch_backend import DEFAULT_CHECKPOINT

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "examples" / "fast_motion_250x400.dat"


def test_shipped_onnx_is_the_shipped_checkpoint_and_verifies():
    """The shipped default graph holds its checkpoint's weights and matches it on the hard
    content cases and an odd size (the CLI's ``verify --quick`` runs on tiny in test_export)."""
    meta = OnnxModel(threads=1).metadata
    assert meta["weights_sha256"] == weights_sha256(load_checkpoint(DEFAULT_CHECKPOINT)["model"])
    assert json.loads(meta["window"]) == 41 and float(meta["rate"]) == 0.6
    cases = hard_cases.content_cases() + hard_cases.size_cases(((17, 23),), threads=(1,))
    report = verify_onnx(default_model_path(), load_model(DEFAULT_CHECKPOINT), cases)
    assert report.passed and len(report.results) == 7, report.table()


def test_the_shipped_folded_member_verifies_off_its_multiple_and_streams_its_blocks():
    """``cpu`` folds 2x2 patches into channels and pads to a multiple of 16 px: its graph
    against its checkpoint at sizes that are not multiples (nor of the fold), and its block
    graphs streamed against the network on whole windows."""
    path = shipped_models()["cpu"]
    model = load_model(path.with_suffix(".pt"))
    assert model.config.sali_stride == 2 and model.config.size_multiple == 16
    report = verify_onnx(path, model, hard_cases.size_cases(((17, 23), (9, 30)), threads=(1,)))
    assert report.passed, report.table()
    assert block_parity(path, model) <= ATOL


def test_every_shipped_model_is_its_checkpoint_with_its_block_graphs():
    """Each ``spk2img-<name>.onnx`` (the names ``--model`` takes), its encoder and head graphs
    and the ``.pt`` beside it hold the same weights, and its card exists."""
    assert {"default", "real"} <= set(shipped_models())
    docs = ROOT / "docs"
    for name, path in shipped_models().items():
        weights = weights_sha256(load_checkpoint(path.with_suffix(".pt"))["model"])
        for graph in (path, path.with_suffix(".encoder.onnx"), path.with_suffix(".head.onnx")):
            assert graph_metadata(graph)["weights_sha256"] == weights, graph
        assert graph_metadata(path)["name"] == f"spk2img-{name}"
        card = "model_card.md" if name == "default" else f"model_card_{name}.md"
        assert f"spk2img/assets/models/spk2img-{name}.onnx" in (docs / card).read_text()


def readme_command() -> list[str]:
    """README's main command (the line that starts ``spk2img reconstruct``), without
    ``spk2img``."""
    readme = (ROOT / "README.md").read_text().splitlines()
    return shlex.split(next(line for line in readme if line.startswith("spk2img reconstruct ")))[1:]


def test_readme_command_and_the_service_agree(tmp_path, monkeypatch):
    """README's command as written (every 7th centre, each block encoded once), run in a folder
    whose ``examples/`` holds the sample stream's first 48 frames (the first 2 of its 12
    centres: the same work per frame, a sixth of the time), and the service on the whole window
    of the last centre (whose blocks the command had all encoded for earlier centres but one),
    give the same frame. (The torch backend's agreement: the shipped graph against its
    checkpoint above, the CLI's backends in tests/test_export.py.)"""
    command = readme_command()
    assert command[1] == "examples/fast_motion_250x400.dat"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").mkdir()
    write_spikes(command[1], read_spikes(SAMPLE, 250, 400)[0:48])
    assert main([*command, "--no-progress"]) == 0
    readme_out, png_dir = tmp_path / "out" / "frames.npz", tmp_path / "out" / "png"
    ran = np.load(readme_out)
    assert ran["centers"].tolist() == [20, 27]
    assert len(list(png_dir.glob("*.png"))) == 2
    assert ran["frames"].shape == (2, 250, 400) and np.isfinite(ran["frames"]).all()
    remote = tmp_path / "remote.npz"
    with run_server(default_model_path(), "--threads", "2") as server:
        args = ["reconstruct", command[1], "--out", str(remote), "--centers", "27"]
        assert main([*args, "--url", server.url, "--no-progress"]) == 0
    np.testing.assert_allclose(np.load(remote)["frames"], ran["frames"][-1:], atol=1e-5)
