"""Devices (docs/gpu.md): provider selection, the error path where a GPU provider is missing,
``auto``, IO binding (run on the CPU provider here), the service setting and the CLI flags.

Everything but the tests marked ``needs_cuda`` runs on any machine; those skip with a reason
where onnxruntime has no CUDA provider that starts.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.runtime import onnx_backend
from spk2img.runtime.block_codec import OnnxBlockCodec
from spk2img.runtime.onnx_backend import (
    DeviceError,
    OnnxModel,
    create_session,
    default_model_path,
    provider_chain,
    resolve_device,
)

CPU_ONLY = ["AzureExecutionProvider", "CPUExecutionProvider"]
WITH_CUDA = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]


def _cuda_starts() -> bool:
    if "CUDAExecutionProvider" not in onnx_backend.available_providers():
        return False
    try:
        create_session(default_model_path(), 1, "cuda")
    except DeviceError:
        return False
    return True


HAS_CUDA = _cuda_starts()
needs_cuda = pytest.mark.skipif(
    not HAS_CUDA, reason="no GPU: onnxruntime here has no CUDA provider that starts"
)
no_cuda = pytest.mark.skipif(HAS_CUDA, reason="a CUDA provider runs here: no error to check")


@pytest.fixture(scope="module")
def windows() -> np.ndarray:
    return (np.random.default_rng(19).random((2, 41, 24, 36)) < 0.3).astype(np.float32)


def test_named_devices_map_to_their_providers_first():
    assert [name for name, _ in provider_chain("cpu")] == ["CPUExecutionProvider"]
    assert [name for name, _ in provider_chain("cuda")] == [
        "CUDAExecutionProvider",
        "CPUExecutionProvider",
    ]
    trt = provider_chain("tensorrt", fp16=True)
    assert [name for name, _ in trt] == WITH_CUDA
    assert trt[0][1]["trt_fp16_enable"] == "True" and trt[0][1]["trt_engine_cache_enable"]
    with pytest.raises(ValueError):
        provider_chain("auto")


def test_auto_prefers_cuda_and_says_what_it_chose():
    assert resolve_device("auto", WITH_CUDA)[0] == "cuda"
    device, note = resolve_device("auto", CPU_ONLY)
    assert device == "cpu" and "auto chose cpu" in note and "CUDAExecutionProvider" in note
    assert resolve_device("cuda", WITH_CUDA) == ("cuda", "")
    assert resolve_device("cpu", CPU_ONLY) == ("cpu", "")


def test_a_missing_gpu_provider_is_one_line_naming_the_fix():
    for device in ("cuda", "tensorrt"):
        with pytest.raises(DeviceError) as caught:
            resolve_device(device, CPU_ONLY)
        message = str(caught.value)
        assert "\n" not in message and "[gpu]" in message and "--device auto" in message
    with pytest.raises(DeviceError, match="TensorRT's libraries"):
        resolve_device("tensorrt", ["CUDAExecutionProvider", "CPUExecutionProvider"])
    with pytest.raises(InputError, match="unknown device"):
        resolve_device("gpu", CPU_ONLY)
    assert isinstance(DeviceError("x"), InputError)  # the CLI's exit code 2


def test_a_provider_that_falls_back_quietly_is_caught(monkeypatch):
    """onnxruntime-gpu without a GPU lists CUDA but runs the session on the CPU: ``cuda`` is
    then an error and ``auto`` says it chose the CPU."""
    if HAS_CUDA:
        pytest.skip("CUDA starts here: nothing falls back")
    monkeypatch.setattr(onnx_backend, "available_providers", lambda: WITH_CUDA)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # onnxruntime warns that the provider is unavailable
        with pytest.raises(DeviceError, match="could not start it"):
            create_session(default_model_path(), 1, "cuda")
        session = create_session(default_model_path(), 1, "auto")
    assert session.device == "cpu" and session.provider == "CPUExecutionProvider"
    assert "auto chose cpu" in session.note and "could not start" in session.note


@no_cuda
def test_cuda_where_there_is_none_fails_at_load_and_auto_runs_on_cpu():
    for device in ("cuda", "tensorrt"):
        with pytest.raises(DeviceError):
            OnnxModel(threads=1, device=device)
        with pytest.raises(DeviceError):
            OnnxBlockCodec(threads=1, device=device)
    model = OnnxModel(threads=1, device="auto")
    assert (model.device, model.provider) == ("cpu", "CPUExecutionProvider")
    assert "auto chose cpu" in model.device_note and not model.io_binding


def test_io_binding_gives_the_plain_run_bit_for_bit_on_cpu(windows):
    plain, bound = OnnxModel(threads=1), OnnxModel(threads=1, io_binding=True)
    assert not plain.io_binding and bound.io_binding
    assert np.array_equal(plain(windows), bound(windows))
    codecs = OnnxBlockCodec(threads=1), OnnxBlockCodec(threads=1, io_binding=True)
    codes = [codec.encode(windows[0, :13]) for codec in codecs]
    for a, b in zip(*codes, strict=True):
        assert np.array_equal(a, b)
    images = [codec.head([code] * 5, 24, 36) for codec, code in zip(codecs, codes, strict=True)]
    assert np.array_equal(*images)


def test_a_batch_of_centres_per_call_equals_one_at_a_time(windows):
    model = OnnxModel(threads=1)
    both = model(windows)
    one_by_one = np.concatenate([model(windows[i : i + 1]) for i in range(len(windows))])
    assert np.allclose(both, one_by_one, atol=1e-5)


def test_reconstruct_device_flags(tmp_path, capsys):
    spikes = tmp_path / "s.npy"
    np.save(spikes, (np.random.default_rng(1).random((50, 16, 20)) < 0.3).astype(np.uint8))
    out = tmp_path / "o.npz"
    if not HAS_CUDA:
        assert main(["reconstruct", str(spikes), "--out", str(out), "--device", "cuda"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "CUDAExecutionProvider" in err, err
        assert main(["reconstruct", str(spikes), "--out", str(out), "--device", "auto"]) == 0
        assert "--device auto chose cpu" in capsys.readouterr().err
    args = ["reconstruct", str(spikes), "--out", str(out), "--no-block-reuse", "--stride", "1"]
    assert main([*args, "--batch", "4", "-q"]) == 0
    batched = np.load(out)["frames"]
    assert main([*args, "-q"]) == 0
    assert np.allclose(batched, np.load(out)["frames"], atol=1e-5)
    assert main([*args, "--batch", "0"]) == 2
    url = ["--url", "http://127.0.0.1:9", "--device", "cpu"]
    assert main(["reconstruct", str(spikes), "--out", str(out), *url]) == 2
    assert "--device" in capsys.readouterr().err


def test_the_service_setting():
    from pydantic import ValidationError

    from spk2img.service.settings import ServiceSettings

    assert ServiceSettings().device == "cpu"
    assert ServiceSettings(device="auto").device == "auto"
    if not HAS_CUDA:
        with pytest.raises(ValidationError, match="CUDAExecutionProvider"):
            ServiceSettings(device="cuda")
    with pytest.raises(ValidationError):
        ServiceSettings(device="gpu")


@no_cuda
def test_serve_refuses_to_start_on_a_missing_gpu(capsys, monkeypatch):
    monkeypatch.setenv("SPK2IMG_DEVICE", "tensorrt")
    assert main(["serve", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--device (SPK2IMG_DEVICE)" in err, err


@needs_cuda
def test_cuda_runs_the_graphs_close_to_the_cpu(windows):
    cpu, cuda = OnnxModel(threads=1), OnnxModel(threads=1, device="cuda")
    assert (cuda.device, cuda.provider, cuda.io_binding) == ("cuda", "CUDAExecutionProvider", True)
    assert np.abs(cuda(windows) - cpu(windows)).max() < 1e-3
    codec = OnnxBlockCodec(threads=1, device="cuda")
    reference = OnnxBlockCodec(threads=1)
    codes = [c.encode(windows[0, :13]) for c in (codec, reference)]
    images = [c.head([code] * 5, 24, 36) for c, code in zip((codec, reference), codes, strict=True)]
    assert np.abs(images[0] - images[1]).max() < 1e-3
    assert OnnxModel(threads=1, device="auto").device == "cuda"
