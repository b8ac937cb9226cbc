"""Block-feature reuse: the block encoder and the align-and-fuse head, streamed so that each
13-frame block is encoded once, give the one-shot network's frames (torch and ONNX, CLI and
service), in bounded memory, and only where centres really share blocks."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from service_support import run_server

from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.runtime.block_codec import OnnxBlockCodec, block_graph_paths
from spk2img.runtime.block_stream import BlockReuseStream, reuses_blocks
from spk2img.runtime.methods import build_reconstructor, method_plan
from spk2img.runtime.onnx_backend import OnnxModel, default_model_path
from spk2img.runtime.stream import NetStream, collect, frame_chunks, run_stream
from spk2img.runtime.torch_backend import TorchPredictor
from spk2img.runtime.windows import CenterPlan
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, simulate

HEIGHT, WIDTH = 26, 35  # not multiples of the pyramid's 2: the padding is exercised


@pytest.fixture(scope="module")
def scene_stream():
    """A fast-moving simulated scene, real-like sensor: ``(120, 26, 35)`` uint8."""
    rng = np.random.default_rng(4242)
    scene = random_scene(rng, HEIGHT, WIDTH, "fast", "normal")
    return simulate(scene, 120, SensorConfig.real(), rng)


@pytest.fixture(scope="module")
def torch_model():
    return TorchPredictor(threads=1)


def _stream(spikes, plan, predict, codec=None, chunk=17):
    recon = build_reconstructor("net", *spikes.shape[1:], plan, predict, codec=codec)
    frames, centers = collect(run_stream(recon, frame_chunks(spikes, chunk)), *spikes.shape[1:])
    return recon, frames, centers


@pytest.mark.parametrize(
    "centers, stride",
    [(None, 7), (None, 14), (None, 28), ("27,34,48,76,97", None)],
)
def test_torch_reuse_equals_whole_windows(scene_stream, torch_model, centers, stride):
    plan = method_plan("net", centers, stride)
    whole, expected, want = _stream(scene_stream, plan, torch_model)
    reuse, frames, got = _stream(scene_stream, plan, torch_model, codec=torch_model)
    assert isinstance(whole, NetStream) and isinstance(reuse, BlockReuseStream)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(frames, expected, atol=1e-5)
    # each block that some centre needs is encoded once; a stream does not know its end, so
    # the first blocks of a centre the stream ends too early for may be encoded too
    starts = {int(k) + s for k in want for s in reuse.starts}
    assert len(starts) <= reuse.blocks_encoded <= len(starts) + 4  # 4 = blocks - 1
    assert reuse.codes_held == 0  # closed: nothing held


def test_codes_held_stay_bounded_on_a_long_stream(torch_model):
    spikes = (np.random.default_rng(1).random((400, 8, 12)) < 0.3).astype(np.uint8)
    recon = build_reconstructor(
        "net", 8, 12, CenterPlan(41, stride=7), torch_model, codec=torch_model
    )
    held = []
    for chunk in frame_chunks(spikes, 5):
        recon.push(chunk)
        held.append(recon.codes_held)
    recon.close()
    assert max(held) <= 5 and recon.blocks_encoded == (400 - 13) // 7 + 1


@settings(max_examples=200, deadline=None)
@given(
    stride=st.integers(1, 60),
    gaps=st.lists(st.integers(1, 60), min_size=0, max_size=6),
    first=st.integers(20, 60),
)
def test_reuse_only_when_centres_share_blocks(torch_model, stride, gaps, first):
    """Block reuse is chosen exactly when the centres lie on one 7-frame grid and two of them
    share a block (are less than 35 frames apart)."""
    assert reuses_blocks(CenterPlan(41, stride=stride), torch_model) == (
        stride % 7 == 0 and stride < 35
    )
    centers = np.cumsum([first, *gaps])
    plan = CenterPlan(41, centers=centers.tolist())
    diffs = np.diff(np.unique(centers))
    shares = diffs.size > 0 and all(d % 7 == 0 for d in diffs) and diffs.min() < 35
    assert reuses_blocks(plan, torch_model) == shares


def test_shipped_block_graphs_equal_the_shipped_one_shot_graph(scene_stream):
    model = OnnxModel(threads=1)
    codec = OnnxBlockCodec(threads=1)
    assert codec.metadata["weights_sha256"] == model.metadata["weights_sha256"]
    assert {
        codec.metadata["part"],
        codec.head_session.get_modelmeta().custom_metadata_map["part"],
    } == {"encoder", "head"}
    plan = CenterPlan(41, stride=7)
    _, expected, want = _stream(scene_stream, plan, model)
    reuse, frames, got = _stream(scene_stream, plan, model, codec=codec)
    assert isinstance(reuse, BlockReuseStream)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(frames, expected, atol=1e-5)
    assert np.isfinite(frames).all() and frames.std() > 0.01  # a real picture, not a constant


def test_parts_of_different_models_are_refused(tmp_path, three_block_export):
    """An encoder and a head holding different weights never run together."""
    for part, path in block_graph_paths(default_model_path()).items():
        (tmp_path / f"m.{part}.onnx").write_bytes(path.read_bytes())
    tmp_path.joinpath("m.onnx").write_bytes(default_model_path().read_bytes())
    OnnxBlockCodec(tmp_path / "m.onnx")  # the copy loads
    other_head = block_graph_paths(three_block_export)["head"]
    (tmp_path / "m.head.onnx").write_bytes(other_head.read_bytes())
    with pytest.raises(InputError, match="different weights"):
        OnnxBlockCodec(tmp_path / "m.onnx")


def test_cli_reuse_equals_no_reuse_and_service_equals_cli(tmp_path, scene_stream, capsys):
    source = tmp_path / "s.npy"
    np.save(source, scene_stream)
    outs = {}
    variants = {"reuse": [], "whole": ["--no-block-reuse"], "torch": ["--backend", "torch"]}
    for name, extra in variants.items():
        outs[name] = tmp_path / f"{name}.npz"
        args = ["reconstruct", str(source), "--out", str(outs[name]), "--stride", "7"]
        assert main([*args, "--no-progress", "--threads", "1", *extra]) == 0
    with run_server(default_model_path(), "--threads", "1") as server:
        models = server.get("/v1/models").json()["models"][0]
        assert models["block_graphs"] == [
            "spk2img-default.encoder.onnx",
            "spk2img-default.head.onnx",
        ]
        outs["remote"] = tmp_path / "remote.npz"
        args = ["reconstruct", str(source), "--out", str(outs["remote"]), "--stride", "7"]
        assert main([*args, "--url", server.url, "--no-progress"]) == 0
    frames = {k: np.load(v)["frames"] for k, v in outs.items()}
    assert frames["reuse"].shape == (12, HEIGHT, WIDTH)
    err = capsys.readouterr().err
    assert "each 13-frame block encoded once: 16 blocks" in err  # starts 0, 7 .. 105
    np.testing.assert_allclose(frames["reuse"], frames["whole"], atol=1e-5)
    np.testing.assert_allclose(frames["torch"], frames["whole"], atol=1e-5)
    np.testing.assert_array_equal(frames["remote"], frames["reuse"])
