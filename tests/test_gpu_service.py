"""The service's device (docs/gpu.md): ``/readyz`` and ``/v1/models`` name the provider in use,
``auto`` runs where it can, and a GPU device that cannot start stops the service at start."""

from __future__ import annotations

import time
import warnings

import pytest
from fastapi.testclient import TestClient

from spk2img.runtime import onnx_backend
from spk2img.runtime.onnx_backend import DeviceError
from spk2img.service.app import create_app
from spk2img.service.settings import ServiceSettings

HAS_CUDA = "CUDAExecutionProvider" in onnx_backend.available_providers()


def _ready(client: TestClient) -> dict:
    deadline = time.monotonic() + 30
    while (answer := client.get("/readyz")).status_code != 200:
        assert time.monotonic() < deadline, answer.text
        time.sleep(0.05)
    return answer.json()


def test_auto_reports_the_provider_it_chose(standin_model):
    settings = ServiceSettings(model=standin_model, device="auto", threads=1)
    with TestClient(create_app(settings)) as client:
        ready = _ready(client)
        (info,) = client.get("/v1/models").json()["models"]
    expected = ("cuda", "CUDAExecutionProvider") if HAS_CUDA else ("cpu", "CPUExecutionProvider")
    assert (ready["status"], ready["device"], ready["provider"]) == ("ready", *expected)
    assert (info["device"], info["provider"]) == expected


def test_a_gpu_that_cannot_start_stops_the_service(standin_model, monkeypatch):
    if HAS_CUDA:
        pytest.skip("onnxruntime here has CUDA: nothing to refuse")
    # onnxruntime-gpu on a machine without a GPU lists CUDA, then runs on the CPU quietly
    monkeypatch.setattr(onnx_backend, "available_providers", lambda: ["CUDAExecutionProvider"])
    settings = ServiceSettings(model=standin_model, device="cuda", threads=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(DeviceError, match="could not start it"):
            with TestClient(create_app(settings)):
                pass
