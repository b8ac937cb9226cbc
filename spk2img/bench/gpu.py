"""The GPU rows of the benchmark: the shipped and ``paper`` networks on onnxruntime's CUDA (or
TensorRT) provider, fp32 and fp16, one-shot (one and :data:`BATCH` centres per call, and the
self-ensemble's four mirrored views of one centre in one call) and streamed with block reuse,
and the service's frames/s with :data:`SERVICE_CLIENTS` clients.

They run only where a CUDA provider starts (:func:`gpu_device`); elsewhere the report lists the
same rows as not yet measured, never with a figure. Each row runs in a fresh worker process
(:func:`spk2img.bench.worker.measure_gpu`) and names the GPU it ran on.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .worker import WorkerError, run_job

WEIGHTS = ("shipped", "paper")
"""Networks timed on the GPU: the shipped model and the paper-sized member (random weights)."""
PRECISIONS = ("fp32", "fp16")
BATCH = 8
"""Centres per call of the batched one-shot rows (the one-shot graph's batch axis is dynamic)."""
SELF_ENSEMBLE = "one-shot, self-ensemble"
"""The mode of the rows that run one centre's four mirrored views as one call."""
MODES = {"one-shot": 1, f"one-shot, {BATCH} per call": BATCH, SELF_ENSEMBLE: 1, "streamed": 0}
"""Row mode -> centres per one-shot call (0: streamed, each 13-frame block encoded once)."""
SERVICE_CLIENTS = 4
NO_GPU = "not yet measured (no GPU on the machine that ran this bench)"
WORKER_TIMEOUT_S = 3600


def planned_rows() -> list[dict]:
    """Every GPU row, unmeasured: ``weights``, ``precision``, ``mode`` and ``batch``."""
    return [
        {"weights": w, "precision": p, "mode": mode, "batch": batch}
        for w in WEIGHTS
        for p in PRECISIONS
        for mode, batch in MODES.items()
    ]


def not_measured(reason: str = NO_GPU) -> dict:
    """The GPU section of a run that measured none of it, and why."""
    return {"device": None, "gpu": None, "error": reason, "rows": planned_rows(), "service": None}


def gpu_name() -> str:
    """The GPU's name from ``nvidia-smi`` (``CUDA device 0`` when it cannot say)."""
    smi = shutil.which("nvidia-smi")
    if smi:
        try:
            done = subprocess.run(
                [smi, "--query-gpu=name", "--format=csv,noheader"],
                capture_output=True,
                text=True,
                timeout=30,
            )
            names = done.stdout.strip().splitlines()
            if done.returncode == 0 and names:
                return names[0].strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return "CUDA device 0"


def gpu_device(requested: str, model: Path) -> tuple[str | None, str]:
    """The device the GPU rows run on for ``--device requested``, or ``None`` and why not.

    ``cpu``: none (the GPU rows are skipped). ``auto``: ``cuda`` when a CUDA session of
    ``model`` starts here, else none. ``cuda``/``tensorrt``: that device, or
    :class:`~spk2img.runtime.onnx_backend.DeviceError` (the command stops at once, exit 2).
    """
    from spk2img.runtime.onnx_backend import DeviceError, create_session

    if requested == "cpu":
        return None, "not measured (--device cpu)"
    try:
        session = create_session(model, 1, "cuda" if requested == "auto" else requested)
    except DeviceError as exc:
        if requested != "auto":
            raise
        return None, f"{NO_GPU}: {exc}"
    return session.device, ""


def gpu_benchmark(
    device: str,
    weights: dict[str, Path],
    cases_dir: Path,
    stream: Path,
    threads: int,
    repeats: int,
    work: Path,
    log: Callable[[str], None],
) -> dict:
    """Measure every planned row on ``device`` (a concrete GPU device) for the fp32 one-shot
    graphs in ``weights`` (``{name: path}``, block graphs beside), their fp16 conversions made
    in ``work``, the benchmark windows in ``cases_dir`` and the ``(T, H, W)`` ``stream``."""
    from spk2img.export.quantize import reduce_block_graphs, reduce_precision

    graphs: dict[tuple[str, str], Path] = {}
    for name, fp32 in weights.items():
        graphs[name, "fp32"] = fp32
        fp16 = work / f"gpu-{name}-fp16.onnx"
        reduce_precision(fp32, fp16, "fp16")
        reduce_block_graphs(fp32, fp16, "fp16")
        graphs[name, "fp16"] = fp16
    rows = []
    for row in planned_rows():
        path = graphs.get((row["weights"], row["precision"]))
        if path is None:
            rows.append({**row, "error": f"no {row['weights']} graph to run"})
            continue
        spec = {
            "job": "gpu",
            "model": str(path),
            "device": device,
            "batch": row["batch"],
            "self_ensemble": row["mode"] == SELF_ENSEMBLE,
            "threads": [threads],
            "repeats": repeats,
            "cases": str(cases_dir),
            "spikes": str(stream),
        }
        try:
            result = run_job(spec, WORKER_TIMEOUT_S)
        except WorkerError as exc:
            rows.append({**row, "error": str(exc)})
            log(f"GPU {row['weights']} {row['precision']} {row['mode']}: failed ({exc})")
            continue
        rows.append({**row, **result, "error": None})
        log(
            f"GPU {row['weights']} {row['precision']} {row['mode']}: "
            f"{result['ms_per_frame']:.2f} ms/frame on {result['provider']}"
        )
    return {"device": device, "gpu": gpu_name(), "error": None, "rows": rows, "service": None}


def gpu_service(
    device: str, model: Path, window: np.ndarray, threads: int, requests: int, log
) -> dict:
    """The service on ``device`` with :data:`SERVICE_CLIENTS` concurrent clients (the CPU
    load test's method, :func:`spk2img.bench.service_load.service_benchmark`); an ``error``
    when the service did not run the model on that device."""
    from .service_load import service_benchmark

    log(f"load-testing the service on {device} with {SERVICE_CLIENTS} clients")
    try:
        result = service_benchmark(
            model, window, threads, (SERVICE_CLIENTS,), requests, device=device
        )
    except (RuntimeError, OSError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    return result
