"""The GPU rows of the benchmark: the shipped networks of each architecture and the ``paper``
member on onnxruntime's CUDA (or TensorRT) provider, fp32 and fp16, one-shot (one, 8 and 32
centres per call, and the self-ensemble's four mirrored views of one centre in one call) and
streamed with block reuse, and the service's frames/s with 1 and 4 concurrent clients.

They run only where a CUDA provider starts (:func:`gpu_device`); elsewhere the report lists the
same rows as not yet measured, never with a figure. Each row runs in a fresh worker process
(:func:`spk2img.bench.worker.measure_gpu`) and names the GPU it ran on; the rows measured so
far can be written after each one (``on_row``), so a run cut short keeps them.
"""

from __future__ import annotations

import functools
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .worker import WorkerError, run_job

WEIGHTS = ("shipped", "tiny", "cpu", "paper")
"""Networks timed on the GPU, in this order: the shipped default, the shipped models of the two
other architectures (``real`` and ``tiny-real`` run default's and tiny's graphs), and the
paper-sized member (random weights, :data:`UNTRAINED`)."""
UNTRAINED = ("paper",)
PRECISIONS = ("fp32", "fp16")
BATCHES = (8, 32)
"""Centres per call of the batched one-shot rows (the one-shot graph's batch axis is dynamic)."""
SELF_ENSEMBLE = "one-shot, self-ensemble"
"""The mode of the rows that run one centre's four mirrored views as one call."""
MODES = {
    "one-shot": 1,
    **{f"one-shot, {batch} per call": batch for batch in BATCHES},
    SELF_ENSEMBLE: 1,
    "streamed": 0,
}
"""Row mode -> centres per one-shot call (0: streamed, each 13-frame block encoded once)."""
SERVICE_CLIENTS = (1, 4)
"""Concurrent clients of the service's rows."""
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
    section: dict,
    graphs: dict[str, Callable[[], Path]],
    job: dict,
    work: Path,
    log: Callable[[str], None],
    on_row: Callable[[dict], None] | None = None,
) -> dict:
    """Measure every planned row into ``section`` (:func:`measured_section`): each network of
    ``graphs`` (``{name: make}``, ``make()`` gives its fp32 one-shot graph with its block graphs
    beside, called when its first row comes) in fp32 and converted to fp16 in ``work``, by
    workers running ``job`` (device, threads, repeats, the benchmark windows and stream);
    ``on_row`` gets ``section`` after each row. A graph that cannot be made fails its rows,
    not the run."""
    graph = row_graphs(graphs, work, log)
    for row in planned_rows():
        section["rows"].append(measured_row(row, graph(row["weights"], row["precision"]), job, log))
        if on_row is not None:
            on_row(section)
    return section


def measured_section(device: str) -> dict:
    """The GPU section before its rows: the device and the GPU's name."""
    return {"device": device, "gpu": gpu_name(), "error": None, "rows": [], "service": None}


def row_graphs(
    graphs: dict[str, Callable[[], Path]], work: Path, log: Callable[[str], None]
) -> Callable[[str, str], Path | None]:
    """``graph(name, precision)``: the one-shot graph of a row, made once on first use (fp16:
    the fp32 graph and its block graphs converted into ``work``), or ``None`` where it could
    not be made (logged)."""
    from spk2img.export.quantize import reduce_block_graphs, reduce_precision

    def fp16_of(name: str) -> Path | None:
        fp32 = graph(name, "fp32")
        if fp32 is None:  # already logged
            return None
        fp16 = work / f"gpu-{name}-fp16.onnx"
        reduce_precision(fp32, fp16, "fp16")
        reduce_block_graphs(fp32, fp16, "fp16")
        return fp16

    @functools.cache
    def graph(name: str, precision: str) -> Path | None:
        try:
            return graphs[name]() if precision == "fp32" else fp16_of(name)
        except Exception as exc:  # noqa: BLE001 - its rows report the failure
            log(f"the {precision} graph of {name} for the GPU rows failed: {exc}")
            return None

    return graph


def measured_row(row: dict, graph: Path | None, job: dict, log: Callable[[str], None]) -> dict:
    """Planned ``row`` measured on ``graph`` by a worker running ``job`` (the device, threads,
    repeats and data), or with the ``error`` that stopped it."""
    if graph is None:
        return {**row, "error": f"no {row['weights']} graph to run"}
    spec = {**job, "model": str(graph), "batch": row["batch"]}
    spec["self_ensemble"] = row["mode"] == SELF_ENSEMBLE
    try:
        result = run_job(spec, WORKER_TIMEOUT_S)
    except WorkerError as exc:
        log(f"GPU {row['weights']} {row['precision']} {row['mode']}: failed ({exc})")
        return {**row, "error": str(exc)}
    log(
        f"GPU {row['weights']} {row['precision']} {row['mode']}: "
        f"{result['ms_per_frame']:.2f} ms/frame on {result['provider']}"
    )
    return {**row, **result, "error": None}


def gpu_service(
    device: str, model: Path, window: np.ndarray, threads: int, requests: int, log
) -> dict:
    """The service on ``device`` with each of :data:`SERVICE_CLIENTS` concurrent clients (the
    CPU load test's method, :func:`spk2img.bench.service_load.service_benchmark`); an ``error``
    when the service did not run the model on that device."""
    from .service_load import service_benchmark

    log(f"load-testing the service on {device} with {SERVICE_CLIENTS} clients")
    try:
        result = service_benchmark(model, window, threads, SERVICE_CLIENTS, requests, device=device)
    except (RuntimeError, OSError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    return result
