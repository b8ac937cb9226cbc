"""The model carries its geometry (spk2img.model.config.Geometry): the published values, the
properties every geometry has, and a member with another window (three blocks: 27 frames)
exported, verified and run end to end through the Python API, the CLI, the service and the
client, none of which is told its window."""

from __future__ import annotations

import json
from dataclasses import replace

import httpx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from onnx_models import THREE_BLOCKS
from service_support import run_server

import spk2img
from spk2img.cli import main
from spk2img.model.checkpoint import config_to_dict
from spk2img.model.config import MEMBERS, PUBLISHED_GEOMETRY, Geometry
from spk2img.runtime.onnx_backend import OnnxModel, graph_geometry

FRAMES, HEIGHT, WIDTH = 64, 12, 16


def test_the_published_geometry():
    g = PUBLISHED_GEOMETRY
    assert (g.window_frames, g.block_frames, g.block_stride, g.num_blocks) == (41, 13, 7, 5)
    assert g.half == 20
    assert g.block_starts == (-20, -13, -6, 1, 8)
    assert g.block_centres == (6, 13, 20, 27, 34)
    assert all(MEMBERS[m].geometry.window_frames == 41 for m in MEMBERS)
    assert MEMBERS["small"].geometry.size_multiple == 4 and MEMBERS["lite"].size_multiple == 8
    assert MEMBERS["cpu"].size_multiple == 16


@given(
    block_frames=st.integers(0, 10).map(lambda n: 2 * n + 1),
    block_stride=st.integers(1, 20),
    num_blocks=st.integers(0, 4).map(lambda n: 2 * n + 1),
)
def test_blocks_tile_a_centred_window(block_frames, block_stride, num_blocks):
    g = Geometry(block_frames, block_stride, num_blocks)
    assert g.window_frames % 2 == 1
    assert g.block_starts[0] == -g.half  # the first block starts the window ...
    assert g.block_starts[-1] + block_frames - 1 == g.half  # ... and the last one ends it
    assert g.block_centres[num_blocks // 2] == g.half  # the key block is centred
    assert np.all(np.diff(g.block_starts) == block_stride)
    window = np.arange(g.window_frames + 6)
    assert np.array_equal(g.crop(window), np.arange(3, 3 + g.window_frames))


def test_a_geometry_that_cannot_centre_a_window_is_refused():
    with pytest.raises(ValueError, match="odd"):
        Geometry(block_frames=12, block_stride=7, num_blocks=5)
    with pytest.raises(ValueError, match="odd"):
        replace(MEMBERS["tiny"], num_blocks=4)
    with pytest.raises(ValueError, match="no centred"):
        PUBLISHED_GEOMETRY.crop(np.zeros((27, 2, 2)))


def test_graph_geometry_reads_the_config_or_else_the_input():
    config = {"config": json.dumps(config_to_dict(THREE_BLOCKS))}
    assert graph_geometry(config, ["batch", 27, "height", "width"]) == THREE_BLOCKS.geometry
    assert graph_geometry({}, ["B", 41, "H", "W"]).window_frames == 41  # a graph from elsewhere
    with pytest.raises(ValueError, match="odd number of frames"):
        graph_geometry({}, ["B", "frames", "H", "W"])


@pytest.fixture(scope="module")
def stream() -> np.ndarray:
    return (np.random.default_rng(5).random((FRAMES, HEIGHT, WIDTH)) < 0.3).astype(np.uint8)


def _whole_windows(model_path, spikes, centers) -> np.ndarray:
    """The one-shot graph on each centre's 27 frames, cut here by hand."""
    windows = np.stack([spikes[k - 13 : k + 14] for k in centers]).astype(np.float32)
    assert windows.shape[1] == 27
    return OnnxModel(model_path, threads=1)(windows)


def test_a_three_block_member_runs_through_api_cli_and_service(
    three_block_export, stream, tmp_path, capsys
):
    assert OnnxModel(three_block_export, threads=1).geometry == THREE_BLOCKS.geometry
    # the API: default stride = the model's block stride, from its first full 27-frame window
    frames, centers = spk2img.reconstruct(stream, model=three_block_export, threads=1)
    assert centers.tolist() == list(range(13, FRAMES - 13, 7))
    whole = _whole_windows(three_block_export, stream, centers)
    np.testing.assert_allclose(frames, whole, atol=1e-5)  # block reuse = whole windows
    recon = spk2img.Reconstructor("net", model=three_block_export, block_reuse=False, threads=1)
    np.testing.assert_array_equal(
        recon.reconstruct(stream, centers=[13, 50]).frames,
        _whole_windows(three_block_export, stream, [13, 50]),
    )
    with pytest.raises(ValueError, match="first valid centre is 13"):
        recon.reconstruct(stream, centers=[12])
    # the CLI, without a stride
    source, out = tmp_path / "s.npy", tmp_path / "cli.npz"
    np.save(source, stream)
    args = ["reconstruct", str(source), "--out", str(out), "--model", str(three_block_export)]
    assert main([*args, "--threads", "1", "--no-progress"]) == 0
    assert "each 13-frame block encoded once: 8 blocks" in capsys.readouterr().err
    cli = np.load(out)
    np.testing.assert_array_equal(cli["centers"], centers)
    np.testing.assert_array_equal(cli["frames"], frames)
    # the service and the CLI through it: the geometry comes from GET /v1/models
    with run_server(three_block_export, "--threads", "1") as server:
        model = server.get("/v1/models").json()["models"][0]
        assert model["window"] == 27
        assert model["geometry"] == {**THREE_BLOCKS.geometry.as_dict()}
        remote = tmp_path / "remote.npz"
        args = ["reconstruct", str(source), "--out", str(remote), "--url", server.url]
        assert main([*args, "--no-progress"]) == 0
        np.testing.assert_array_equal(np.load(remote)["frames"], frames)
        np.testing.assert_array_equal(np.load(remote)["centers"], centers)
        spk2img.write_spikes(tmp_path / "s.dat", stream[:30])
        refused = httpx.post(
            f"{server.url}/v1/reconstruct?height={HEIGHT}&width={WIDTH}&centers=12",
            content=(tmp_path / "s.dat").read_bytes(),
            headers={"Content-Type": "application/octet-stream"},
        )
        assert refused.status_code == 422 and "13" in refused.json()["detail"]
