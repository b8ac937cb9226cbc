"""One benchmark run: the benchmark set, every row measured in its own process, the scores,
the machine's matmul rate and the service under load, gathered into one JSON-able dict."""

from __future__ import annotations

import os
import platform
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from spk2img.evaluation.scoring import score_images
from spk2img.hardware import available_cores, cpu_model
from spk2img.model.config import MEMBERS

from . import artifacts, gpu
from .cases import BENCH_SEED, SCENE_CLASSES, BenchSet, benchmark_set
from .natural import NATURAL_SIZE, NaturalSet, natural_set
from .rows import BACKENDS, CALLS_PER_FRAME, TRAINED_ONLY, NetRow, Row, TfiRow, TfpRow, row_to_json
from .scores import best_tfp_window, max_abs_error, quality
from .service_load import service_benchmark
from .streaming import stream_benchmark, tiers_benchmark
from .worker import WorkerError, run_job

REFERENCE_SIZE = (250, 400)
"""The PKU camera's frame: MACs are reported per frame of this size."""
WORKER_TIMEOUT_S = 3600
SERVICE_LEVELS = (1, 4)
"""Concurrent clients of the service load test."""


@dataclass(frozen=True)
class Scale:
    """How big a run is."""

    height: int
    """Frame height of the benchmark set and the timings (pixels)."""
    width: int
    """Frame width (pixels)."""
    per_class: int
    """Windows per scene class in the benchmark set."""
    repeats: int
    """Timed calls per row and thread count (after one warm-up)."""
    members: tuple[str, ...]
    """Family members benchmarked with random weights."""
    service_requests: int
    """Requests per number of concurrent clients in the service load test."""
    stream_frames: int
    """Frames of the stream of the streaming benchmark."""
    natural_size: tuple[int, int] = NATURAL_SIZE
    """Frame size (height, width) of the natural validation (with ``--data``)."""
    member_backends: tuple[str, ...] = tuple(b for b in BACKENDS if b not in TRAINED_ONLY)
    """Backends the random members run on."""
    trained_backends: tuple[str, ...] = tuple(BACKENDS)
    """Backends the trained weights (the shipped model, ``--checkpoint``) run on."""


FULL = Scale(
    *REFERENCE_SIZE,
    per_class=4,
    repeats=5,
    members=tuple(MEMBERS),
    service_requests=24,
    stream_frames=1000,
)
QUICK = Scale(
    48,
    64,
    per_class=2,
    repeats=2,
    members=("tiny",),
    service_requests=8,
    stream_frames=90,
    natural_size=(32, 48),
    # no export and no quantizing (half a minute to a minute and a half a graph, 20 s for the
    # int8 weights: the export tests' own work, tests/test_export.py): the random member on
    # torch only, the shipped graph as it is and its fp16 variant (a fraction of a second)
    member_backends=("torch",),
    trained_backends=("torch", "onnx", "onnx-fp16", "onnx-ensemble"),
)


@dataclass(frozen=True)
class BenchOptions:
    """What one ``spk2img bench`` measures."""

    scale: Scale
    threads: tuple[int, ...] = (1, 2)
    """Thread counts of every timing."""
    trained: tuple[tuple[str, Path], ...] = ()
    """Extra trained checkpoints ``(name, path)``, benchmarked and scored like the shipped one."""
    service: bool = True
    """Whether to load-test the HTTP service."""
    streaming: bool = True
    """Whether to run the streaming benchmark (block reuse)."""
    stream_models: tuple[str, ...] = ("default",)
    """Shipped models (their names in :func:`~spk2img.runtime.onnx_backend.shipped_models`) that
    the streaming benchmark streams."""
    command: str = "spk2img bench"
    """The command line that reproduces this run (for the report)."""
    natural_data: tuple[Path, ...] = ()
    """Folders holding the natural validation's held-out sources (:mod:`.natural`); none: the
    rows are scored on the simulated benchmark set only."""
    device: str = "auto"
    """Where the GPU rows run (:mod:`spk2img.bench.gpu`): ``auto`` (CUDA where it starts,
    else they are reported as not yet measured), ``cuda``, ``tensorrt`` or ``cpu`` (skipped)."""


Log = Callable[[str], None]


@dataclass(frozen=True)
class Plan:
    """What a run measures, in table order: rows to measure and, in their place, the entries of
    rows that could not be built (an export failed); and every set of network weights."""

    items: list[Row | dict]
    weights: list[artifacts.Weights]


def run_benchmark(options: BenchOptions, log: Log) -> dict:
    """Measure everything ``options`` asks for; see :mod:`spk2img.bench.report` for the fields."""
    scale = options.scale
    started = datetime.now(UTC)
    gpu_choice = gpu_decision(options, log)  # before hours of CPU rows: --device cuda fails now
    with tempfile.TemporaryDirectory(prefix="spk2img-bench-") as tmp:
        work = Path(tmp)
        log(
            f"simulating the benchmark set ({len(SCENE_CLASSES) * scale.per_class} windows of "
            f"{scale.height}x{scale.width})"
        )
        cases = benchmark_set(scale.per_class, scale.height, scale.width)
        cases_dir = cases.save_spikes(work / "cases")
        natural = natural_run(options, log)
        natural_dir = natural.save_spikes(work / "natural") if natural else None
        plan = plan_rows(options, cases, work, log)
        log("measuring the fp32 matmul rate")
        matmul = run_job(
            {"job": "matmul", "threads": list(options.threads), "repeats": scale.repeats}
        )["gflops"]
        entries, images, natural_images = [], {}, {}
        for i, item in enumerate(plan.items):
            if isinstance(item, dict):
                entries.append(item)
                continue
            outputs = work / f"row{i}.npy", work / f"row{i}-natural.npy"
            entries.append(measure(item, options, cases_dir, outputs, natural_dir))
            if entries[-1]["error"] is None:
                images[i] = np.load(outputs[0])
                if outputs[1].is_file():
                    natural_images[i] = np.load(outputs[1])
            log(
                f"[{i + 1}/{len(plan.items)}] {item.label}, {item.backend}: "
                f"{progress_text(entries[-1])}"
            )
        profiles = profile_run(plan.items, options, cases_dir, log)
        score(entries, plan.items, images, cases)
        if natural is not None:
            for i, row_images in natural_images.items():
                entries[i]["natural"] = score_images(row_images, natural.scenes)
        sizes = {"reference": REFERENCE_SIZE, "timed": (scale.height, scale.width)}
        costs = {w.name: artifacts.cost(w, sizes) for w in plan.weights}
        for entry in entries:
            cost = costs.get(entry["weights"], {"params": 0, "macs": None})
            calls = CALLS_PER_FRAME.get(entry["backend"], 1)
            macs = cost["macs"] and {size: calls * n for size, n in cost["macs"].items()}
            entry.update(params=cost["params"], macs=macs)
        service = (
            load_service(options, plan.items, entries, cases, log) if options.service else None
        )
        streaming = streaming_run(options, work, log) if options.streaming else None
        tiers = tiers_run(options, cases, work, log) if options.streaming else None
        on_gpu = gpu_run(options, gpu_choice, cases, cases_dir, work, log)
    return {
        "command": options.command,
        "date": started.isoformat(timespec="seconds"),
        "machine": machine(),
        "settings": {
            "height": scale.height,
            "width": scale.width,
            "repeats": scale.repeats,
            "threads": list(options.threads),
            "reference_size": list(REFERENCE_SIZE),
        },
        "cases": {
            "count": len(cases),
            "classes": list(SCENE_CLASSES),
            "seed": BENCH_SEED,
            "per_class": scale.per_class,
            "sensors": sorted(set(cases.sensors)),
        },
        "natural": natural.describe() if natural else None,
        "networks": [w.describe() for w in plan.weights],
        "shipped_installed": any(w.name == "shipped" for w in plan.weights),
        "matmul_gflops": matmul,
        "rows": entries,
        "profiles": profiles,
        "service": service,
        "streaming": streaming,
        "tiers": tiers,
        "gpu": on_gpu,
    }


def profile_run(items: list, options: BenchOptions, cases_dir: Path, log: Log) -> list[dict]:
    """Where each fp32 ONNX graph's time goes (:mod:`spk2img.bench.profile`), at the largest
    thread count: ``label``, ``run_ms`` and ``ops`` (ms by operator type), or ``error``."""
    threads = [max(options.threads)]
    profiles = []
    for item in items:
        if not (isinstance(item, NetRow) and item.backend == "onnx"):
            continue
        log(f"profiling {item.label}")
        spec = {"job": "profile", "model": item.path, "threads": threads, "cases": str(cases_dir)}
        try:
            profiles.append({"label": item.label, "threads": threads[0], **run_job(spec)})
        except WorkerError as exc:
            profiles.append({"label": item.label, "threads": threads[0], "error": str(exc)})
    return profiles


def natural_run(options: BenchOptions, log: Log) -> NaturalSet | None:
    """The natural validation of ``options.natural_data`` (``None`` without)."""
    if not options.natural_data:
        return None
    height, width = options.scale.natural_size
    natural = natural_set(list(options.natural_data), height, width)
    log(
        f"natural validation: {len(natural.scenes)} windows of {height}x{width} from "
        f"{len(natural.sources)} held-out sources"
    )
    return natural


def run_gpu_only(
    options: BenchOptions, log: Log, on_row: Callable[[dict], None] | None = None
) -> dict:
    """Only the GPU rows (:mod:`spk2img.bench.gpu`), on the benchmark set of ``options``;
    ``on_row`` gets the section measured so far after each row."""
    choice = gpu_decision(options, log)
    scale = options.scale
    with tempfile.TemporaryDirectory(prefix="spk2img-bench-") as tmp:
        work = Path(tmp)
        cases = benchmark_set(scale.per_class, scale.height, scale.width)
        cases_dir = cases.save_spikes(work / "cases")
        return gpu_run(options, choice, cases, cases_dir, work, log, on_row)


def gpu_decision(options: BenchOptions, log: Log) -> tuple[str | None, str]:
    """The GPU rows' device, or ``None`` and why they are not measured
    (:func:`~spk2img.bench.gpu.gpu_device`, probed with the shipped model's graph)."""
    from spk2img.runtime.onnx_backend import resolve_device

    if options.device in ("cuda", "tensorrt"):
        resolve_device(options.device)  # no such provider: DeviceError, before any work
    shipped = artifacts.shipped()
    if shipped is None:
        return None, "not measured: the shipped model is not installed"
    device, why = gpu.gpu_device(options.device, shipped.onnx)
    log(f"GPU rows on {device}" if device else f"GPU rows: {why}")
    return device, why


def gpu_run(
    options: BenchOptions,
    choice: tuple[str | None, str],
    cases: BenchSet,
    cases_dir: Path,
    work: Path,
    log: Log,
    on_row: Callable[[dict], None] | None = None,
) -> dict:
    """The GPU section: measured on the device of ``choice`` (:func:`gpu_decision`), else the
    planned rows marked not measured with its reason; ``on_row``: as
    :func:`~spk2img.bench.gpu.gpu_benchmark`'s."""
    device, why = choice
    if device is None:
        return gpu.not_measured(why)
    from spk2img.runtime.onnx_backend import shipped_models

    scale = options.scale
    shipped = artifacts.shipped()
    installed = shipped_models()
    graphs = {"shipped": lambda: shipped.onnx}
    graphs |= {n: lambda n=n: installed[n] for n in gpu.WEIGHTS if n in installed}
    graphs["paper"] = lambda: paper_graph(work, log)
    threads = max(options.threads)
    job = {"job": "gpu", "device": device, "threads": [threads], "repeats": scale.repeats}
    job |= {"cases": str(cases_dir), "spikes": str(stream_file(scale, work, log))}
    section = gpu.measured_section(device)
    if options.service:  # before the rows: a run cut short by a time limit keeps it
        window = np.array(cases.spikes[0])
        section["service"] = gpu.gpu_service(
            device, shipped.onnx, window, threads, scale.service_requests, log
        )
        if on_row is not None:
            on_row(section)
    return gpu.gpu_benchmark(section, graphs, job, work, log, on_row)


def paper_graph(work: Path, log: Log) -> Path:
    """The ``paper`` member's one-shot graph with random weights and its block graphs, exported
    into ``work`` for the GPU rows."""
    log("exporting paper (random weights) for the GPU rows")
    path = work / "gpu-paper.onnx"
    artifacts.make_graph(artifacts.random_member("paper", work), "onnx", path, None, True)
    return path


def stream_file(scale: Scale, work: Path, log: Log) -> Path:
    """The streaming benchmark's stream (:func:`stream_spikes` at ``scale``) saved in ``work``,
    simulated on the first call of a run (the streaming and the GPU rows share it)."""
    path = work / "stream.npy"
    if not path.is_file():
        log(
            f"simulating a {scale.stream_frames}-frame {scale.height}x{scale.width} stream "
            "(fast motion, real-like sensor)"
        )
        np.save(path, stream_spikes(scale.stream_frames, scale.height, scale.width))
    return path


def stream_spikes(frames: int, height: int, width: int) -> np.ndarray:
    """The streaming benchmark's stream (fast motion, real-like sensor, its seed)."""
    from spk2img.sim.scenes import random_scene
    from spk2img.sim.simulator import SensorConfig, simulate

    rng = np.random.default_rng([BENCH_SEED, 7])
    scene = random_scene(rng, height, width, "fast", "normal")
    return simulate(scene, frames, SensorConfig.real(), rng)


def run_streaming_only(options: BenchOptions, log: Log) -> dict:
    """Only the streaming benchmark, with the run's command, date and machine."""
    started = datetime.now(UTC)
    scale = options.scale
    with tempfile.TemporaryDirectory(prefix="spk2img-bench-") as tmp:
        streaming = streaming_run(options, Path(tmp), log)
        log(
            f"simulating the benchmark set ({len(SCENE_CLASSES) * scale.per_class} windows of "
            f"{scale.height}x{scale.width})"
        )
        cases = benchmark_set(scale.per_class, scale.height, scale.width)
        tiers = tiers_run(options, cases, Path(tmp), log)
    return {
        "command": options.command,
        "date": started.isoformat(timespec="seconds"),
        "machine": machine(),
        "streaming": streaming,
        "tiers": tiers,
    }


def tiers_run(options: BenchOptions, cases: BenchSet, work: Path, log: Log) -> dict:
    """The quality tiers on the shipped model (``{"error"}`` when it is not installed)."""
    shipped = artifacts.shipped()
    if shipped is None:
        return {"error": "the shipped model is not installed"}
    log("timing the quality tiers on the benchmark set")
    return tiers_benchmark(shipped.onnx, cases, options.threads, work, log)


def streaming_run(options: BenchOptions, work: Path, log: Log) -> list[dict]:
    """The streaming benchmark (:func:`~.streaming.stream_benchmark`) of each of
    ``options.stream_models`` on one simulated stream; ``{"model", "error"}`` for a model that
    is not installed."""
    from spk2img.runtime.onnx_backend import shipped_models

    installed = shipped_models()
    stream = stream_file(options.scale, work, log)
    results = []
    for name in options.stream_models:
        if name not in installed:
            results.append({"model": f"spk2img-{name}", "error": "not installed"})
            continue
        results.append(stream_benchmark(installed[name], stream, options.threads, work, log))
    return results


def plan_rows(options: BenchOptions, cases: BenchSet, work: Path, log: Log) -> Plan:
    """Classical rows first, then each set of weights (random members, the shipped model, the
    trained checkpoints given) by backend, its ONNX graphs exported into ``work``."""
    best = best_tfp_window(cases)
    log(f"best single TFP window on the benchmark set: {best}")
    tfp_rows = [TfpRow(), TfpRow(best, "best single window")]
    if best == tfp_rows[0].window:
        tfp_rows = [TfpRow(best, "also the best single window")]
    items: list[Row | dict] = [*tfp_rows, TfiRow()]
    scale = options.scale
    weights = [artifacts.random_member(m, work) for m in scale.members]
    if (default := artifacts.shipped()) is not None:
        weights.append(default)
    else:
        log("the shipped model is not installed: no shipped rows")
    weights += [artifacts.Weights(name, path, trained=True) for name, path in options.trained]
    for w in weights:
        log(f"exporting {w.name}")
        backends = scale.trained_backends if w.trained else scale.member_backends
        rows, failed = artifacts.net_rows(w, work, backends)
        items += rows
        for backend, reason in failed.items():
            log(f"export of {w.name} for {backend} failed: {reason}")
            items.append(failed_export(w, backend, reason))
    return Plan(items, weights)


def measure(
    row: Row,
    options: BenchOptions,
    cases_dir: Path,
    outputs: tuple[Path, Path],
    natural_dir: Path | None,
) -> dict:
    """Run ``row`` in a worker that saves its images of the benchmark set to ``outputs[0]`` and,
    when it is scored and ``natural_dir`` holds the natural validation, those of the natural
    validation to ``outputs[1]``: the row's entry with its timings and peak RSS, or its
    ``error``."""
    scored = not isinstance(row, NetRow) or row.trained
    spec = {
        "job": "row",
        "row": row_to_json(row),
        "threads": list(options.threads),
        "repeats": options.scale.repeats,
        "warmup": 1,
        "cases": str(cases_dir),
        "score": scored,
        "outputs": str(outputs[0]),
    }
    if scored and natural_dir is not None:
        spec |= {"natural": str(natural_dir), "natural_outputs": str(outputs[1])}
    entry = {
        "label": row.label,
        "kind": row.kind,
        "backend": row.backend,
        "scored": scored,
        "weights": getattr(row, "weights", None),
        "error": None,
    }
    try:
        entry.update(run_job(spec, WORKER_TIMEOUT_S))
    except WorkerError as exc:
        entry["error"] = str(exc)
    return entry


def failed_export(weights: artifacts.Weights, backend: str, reason: str) -> dict:
    """The entry of a row whose ONNX graph could not be made."""
    label = NetRow(weights.name, backend, "", weights.trained).label
    return {
        "label": label,
        "kind": "net",
        "backend": backend,
        "scored": weights.trained,
        "weights": weights.name,
        "error": f"export failed: {reason}",
    }


def score(
    entries: list[dict], items: list[Row | dict], images: dict[int, np.ndarray], cases: BenchSet
) -> None:
    """Add ``quality`` to scored entries and ``max_abs_error`` against the torch row of the same
    weights to network entries, from the ``images`` of each measured item (by index)."""
    reference = {
        item.weights: images.get(i)
        for i, item in enumerate(items)
        if isinstance(item, NetRow) and item.backend == "torch"
    }
    for i, image in images.items():
        item, entry = items[i], entries[i]
        if entry["scored"]:
            entry["quality"] = quality(image, cases)
        if isinstance(item, NetRow) and reference.get(item.weights) is not None:
            entry["max_abs_error"] = max_abs_error(image, reference[item.weights])


def load_service(
    options: BenchOptions, items: list[Row | dict], entries: list[dict], cases: BenchSet, log: Log
) -> dict:
    """The service load test on the shipped model's graph — or, without one, the first trained
    ONNX grid_sample graph that ran, else the first untrained one."""
    served = [
        item
        for item, entry in zip(items, entries, strict=True)
        if isinstance(item, NetRow) and item.backend == "onnx" and entry["error"] is None
    ]
    served.sort(key=lambda row: (row.weights != "shipped", not row.trained))
    if not served:
        return {"error": "no ONNX graph ran, so there is nothing to serve"}
    log(
        f"load-testing the service with {served[0].label} ({', '.join(map(str, SERVICE_LEVELS))} "
        "concurrent clients)"
    )
    try:
        result = service_benchmark(
            Path(served[0].path),
            np.array(cases.spikes[0]),
            max(options.threads),
            SERVICE_LEVELS,
            options.scale.service_requests,
        )
    except (RuntimeError, OSError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"label": served[0].label, **result}


def progress_text(entry: dict) -> str:
    """One line on a measured entry: its median times, or why it failed."""
    if entry["error"]:
        return f"failed ({entry['error']})"
    return ", ".join(
        f"{ms:.1f} ms/frame at {t} thread(s)" for t, ms in entry["ms_per_frame"].items()
    )


def machine() -> dict:
    """CPU model (``/proc/cpuinfo``), cores, memory and software versions of this machine."""
    info = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "memory_gib": None,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    info["cores_available"] = available_cores()
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        total_kib = int(meminfo.read_text().split("MemTotal:")[1].split()[0])
        info["memory_gib"] = round(total_kib / 2**20, 1)
    for package in ("numpy", "torch", "onnxruntime"):
        module = sys.modules.get(package) or __import__(package)
        info[package] = module.__version__
    return info
