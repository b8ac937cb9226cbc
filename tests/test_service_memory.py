"""The service's memory estimate against the peak memory a model call really takes, for thin,
square and wide frames (issue: a 1x100000 frame was admitted at 1.4 GiB and peaked at 3.5)."""

import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from service_support import OCTET, run_server, stream_bytes

import spk2img
from spk2img.model.config import get_config
from spk2img.runtime.allocator import release_free_memory
from spk2img.service.memory import budget_problem, container_limit_bytes
from spk2img.service.reconstruction import NET_BYTES_PER_PIXEL

SHAPES = [(1, 8000), (2, 4000), (8000, 1), (90, 90)]
"""Thin (one and two rows or columns), square and wide frames of about 8,000 pixels."""

_MEASURE = """
import json, sys
import numpy as np
from spk2img.runtime.loader import load_network

def status_kib(field):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field + ":"))

height, width = int(sys.argv[1]), int(sys.argv[2])
network = load_network("default", threads=1, block_reuse=False, warm_up=False)
network.warm_up(8, 8)
window = np.zeros((1, network.geometry.window_frames, height, width), np.float32)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")  # the peak resident size starts again from the present one
before = status_kib("VmRSS")
network.predict(window)
print(json.dumps({"before": before * 1024, "peak": status_kib("VmHWM") * 1024}))
"""


def call_peak_bytes(height: int, width: int) -> int:
    """Bytes a model call of the shipped model at ``height x width`` adds to the process's
    peak resident memory (onnxruntime as the service runs it: arena off)."""
    out = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(height), str(width)],
        capture_output=True,
        text=True,
        check=True,
    )
    measured = json.loads(out.stdout.strip().splitlines()[-1])
    return measured["peak"] - measured["before"]


@pytest.mark.parametrize("shape", SHAPES, ids=[f"{h}x{w}" for h, w in SHAPES])
def test_every_frame_shape_peaks_inside_its_memory_estimate(shape):
    """The model call's peak (beyond the memory held before it) stays under the estimate per
    padded pixel; for one-row and one-column frames it is over an estimate per pixel, what
    let thin frames past the budget."""
    height, width = shape
    geometry = get_config("small").geometry
    padded_height, padded_width = geometry.padded_size(height, width)
    estimate = padded_height * padded_width * NET_BYTES_PER_PIXEL
    peak = call_peak_bytes(height, width)
    assert peak <= estimate, (shape, peak / 2**20, estimate / 2**20)
    if min(shape) == 1:
        assert peak > height * width * NET_BYTES_PER_PIXEL, (shape, peak / 2**20)


def _resident_mib(pid: int) -> float:
    status = Path(f"/proc/{pid}/status").read_text()
    return (
        next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
        / 1024
    )


def test_idle_memory_comes_back_after_a_series_of_large_jobs():
    """``spk2img serve`` with the shipped ``tiny``: idle, then 250x400, 1x20000, 200x300 and
    250x400 network requests one after another, then idle again: its resident memory is back
    within 1.2x of its idle size after start (without the service's release, this series left
    ``tiny`` at 3.4x: 65 -> 221 MiB in one process)."""
    shipped = Path(spk2img.__file__).parent / "assets" / "models" / "spk2img-tiny.onnx"
    with run_server(shipped, "--threads", "2") as server:
        time.sleep(0.5)
        idle = _resident_mib(server.process.pid)
        peaks = []
        for height, width in [(250, 400), (1, 20000), (200, 300), (250, 400)]:
            _, body = stream_bytes(41, height, width, seed=height)
            answer = httpx.post(
                f"{server.url}/v1/reconstruct?height={height}&width={width}&centers=20",
                content=body,
                headers=OCTET,
                timeout=120,
            )
            assert answer.status_code == 200, answer.text
            peaks.append(_resident_mib(server.process.pid))
        time.sleep(1.0)  # the pool trims once the last admission is given back
        after = _resident_mib(server.process.pid)
    print(
        f"\nidle {idle:.0f} MiB, after each job {[round(p) for p in peaks]}, idle after {after:.0f}"
    )
    assert after <= 1.2 * idle, (idle, peaks, after)


def test_the_container_limit_is_read_from_either_cgroup_version(tmp_path):
    v2, v1 = tmp_path / "memory.max", tmp_path / "memory.limit_in_bytes"
    assert container_limit_bytes((v2, v1)) is None  # neither: not in a container
    v1.write_text(f"{2**63 - 4096}\n")  # cgroup v1 without a limit
    assert container_limit_bytes((v2, v1)) is None
    v2.write_text("max\n")
    assert container_limit_bytes((v2, v1)) is None
    v2.write_text(f"{2048 * 2**20}\n")  # docker/compose.yaml's 2048m
    assert container_limit_bytes((v2, v1)) == 2048 * 2**20


def test_a_budget_over_the_container_limit_keeps_the_service_unready_and_says_why():
    """The compose file's budget fits its limit with the idle footprint; a budget that does
    not is named with both sizes (the service logs it and /readyz says it)."""
    limit, idle = 2048 * 2**20, 150 * 2**20
    assert budget_problem(1536 * 2**20, idle, limit) is None
    assert budget_problem(0, idle, limit) is None and budget_problem(2**40, idle, None) is None
    problem = budget_problem(2000 * 2**20, idle, limit)
    assert "2000 MiB plus the 150 MiB" in problem and "limit of 2048 MiB" in problem
    assert release_free_memory()  # glibc here


def test_the_service_checks_its_budget_against_the_container_at_start(monkeypatch, standin_model):
    """In a container whose limit is below the budget the service starts, stays unready and
    its /readyz names both; /healthz still answers."""
    from fastapi.testclient import TestClient

    from spk2img.service import app as service_app
    from spk2img.service.settings import ServiceSettings

    monkeypatch.setattr(service_app, "container_limit_bytes", lambda: 512 * 2**20)
    settings = ServiceSettings(model=standin_model, memory_budget_bytes=1024 * 2**20)
    with TestClient(service_app.create_app(settings)) as client:
        ready = client.get("/readyz")
        assert client.get("/healthz").status_code == 200
    assert ready.status_code == 503
    detail = ready.json()["detail"]
    assert "memory_budget_bytes 1024 MiB" in detail and "limit of 512 MiB" in detail
