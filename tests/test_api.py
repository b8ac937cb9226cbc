"""The public Python API (spk2img.read_spikes, write_spikes, reconstruct, Reconstructor): light
to import, typed results, one loaded model for many streams, and the same frames as the CLI and
the HTTP service."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import spk2img
from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.runtime.loader import load_network
from spk2img.runtime.onnx_backend import default_model_path

H, W = 24, 32


def _stream(frames: int = 55, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rate = rng.uniform(0.05, 0.6, (H, W))
    return (rng.random((frames, H, W)) < rate).astype(np.uint8)


def test_import_spk2img_is_light():
    code = (
        "import sys, spk2img\n"
        "assert 'numpy' not in sys.modules\n"
        "spk2img.reconstruct, spk2img.Reconstructor, spk2img.read_spikes\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('torch', 'onnxruntime', 'fastapi', 'httpx', 'onnx')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert set(spk2img.__all__) >= {"read_spikes", "write_spikes", "reconstruct", "Reconstructor"}
    with pytest.raises(AttributeError):
        spk2img.no_such_name  # noqa: B018


@pytest.mark.parametrize("suffix", [".dat", ".npy", ".npz"])
def test_write_then_read(tmp_path, suffix):
    spikes = _stream(45)
    path = tmp_path / f"s{suffix}"
    spk2img.write_spikes(path, spikes)
    back = spk2img.read_spikes(path, H, W)
    assert back.shape == spikes.shape
    np.testing.assert_array_equal(np.asarray(back[0 : len(back)]), spikes)


def test_reconstruct_returns_frames_and_centres():
    spikes = _stream()
    result = spk2img.reconstruct(spikes, method="tfp")
    frames, centers = result
    assert frames.dtype == np.float32 and frames.shape == (3, H, W)
    assert centers.dtype == np.int64 and centers.tolist() == [20, 27, 34]  # default stride 7
    assert result.frames is frames and 0 <= frames.min() and frames.max() <= 1
    frames, centers = spk2img.reconstruct(spikes, centers=[30, 21], method="tfi")
    assert centers.tolist() == [21, 30]
    assert spk2img.reconstruct(spikes, centers="21,30", method="tfi").centers.tolist() == [21, 30]


def test_bad_calls_are_value_errors():
    spikes = _stream()
    for call in (
        lambda: spk2img.reconstruct(spikes * 2, method="tfp"),
        lambda: spk2img.reconstruct(spikes * 0.5, method="tfp"),
        lambda: spk2img.reconstruct(spikes[:, 0], method="tfp"),
        lambda: spk2img.reconstruct(spikes, centers=[5], method="tfp"),
        lambda: spk2img.reconstruct(spikes, centers=[30], stride=7, method="tfp"),
        lambda: spk2img.Reconstructor("nope"),
        lambda: spk2img.Reconstructor("net", quality="nope"),
    ):
        with pytest.raises(InputError):
            call()
    assert issubclass(InputError, ValueError)


def test_one_reconstructor_many_streams():
    recon = spk2img.Reconstructor("net", threads=1)
    first, second = _stream(55, seed=1), _stream(62, seed=2)
    a = recon.reconstruct(first, stride=14)
    b = recon.reconstruct(second, stride=14)
    assert recon.last_stream is not None and b.centers.tolist() == [20, 34]
    np.testing.assert_array_equal(a.frames, spk2img.reconstruct(first, stride=14, threads=1)[0])
    np.testing.assert_array_equal(b.frames, spk2img.reconstruct(second, stride=14, threads=1)[0])


def test_a_reconstructor_keeps_the_memory_arena_and_a_served_network_does_not():
    """The API's (and CLI's) sessions keep onnxruntime's CPU memory arena, faster for a stream
    of one size; the service's default load does not (a large request must not pin its
    memory); both give the same frames."""
    recon = spk2img.Reconstructor("net", model="tiny", threads=1)
    served = load_network("tiny", threads=1, warm_up=False)
    sessions = {
        "reconstructor": [recon.network.predict.session]
        + [part.session for part in recon.network.codec.parts.values()],
        "served": [served.predict.session] + [part.session for part in served.codec.parts.values()],
    }
    arenas = {
        name: {s.get_session_options().enable_cpu_mem_arena for s in group}
        for name, group in sessions.items()
    }
    assert arenas == {"reconstructor": {True}, "served": {False}}
    windows = _stream(41, seed=3)[None].astype(np.float32)
    np.testing.assert_array_equal(recon.network.predict(windows), served.predict(windows))


@pytest.mark.parametrize(
    "method, quality, placement",
    [("net", "best", ["--stride", "7"]), ("tfp", "best", ["--centers", "22,40"])],
)
def test_api_cli_and_http_give_identical_frames(tmp_path, method, quality, placement):
    from service_support import run_server

    spikes = _stream(61)
    path = tmp_path / "in.npy"
    spk2img.write_spikes(path, spikes)
    flag, value = placement
    kwargs = {"stride": int(value)} if flag == "--stride" else {"centers": value}
    api = spk2img.reconstruct(
        spk2img.read_spikes(path), method=method, quality=quality, threads=1, **kwargs
    )
    args = [str(path), "--method", method, "--quality", quality, *placement, "-q"]
    local = tmp_path / "local.npz"
    assert main(["reconstruct", *args, "--out", str(local), "--threads", "1"]) == 0
    remote = tmp_path / "remote.npz"
    with run_server(default_model_path(), "--threads", "1") as server:
        assert main(["reconstruct", *args, "--out", str(remote), "--url", server.url]) == 0
    for out in (local, remote):
        with np.load(out) as npz:
            np.testing.assert_array_equal(npz["centers"], api.centers)
            np.testing.assert_array_equal(npz["frames"], api.frames)
    assert len(api.centers) >= 2
