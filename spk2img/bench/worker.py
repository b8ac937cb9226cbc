"""Measure one benchmark job in this (fresh) process and print the result as one JSON line.

``python -m spk2img.bench.worker '<json spec>'`` with a spec of one of two jobs:

- ``{"job": "row", "row": ROW, "threads": [1, 2], "repeats": 5, "warmup": 1, "cases": DIR,
  "score": false, "outputs": PATH}``: build the row (:func:`~spk2img.bench.rows.row_from_json`)
  at each thread count, time it on the first window of the benchmark set in ``DIR``, note the
  peak RSS, then save to ``PATH`` (``.npy``) its images of every window (``score``) or of the
  timed window only: ``(N, H, W) float32``. With ``"natural": DIR2, "natural_outputs": PATH2``
  also its images of every window saved in ``DIR2`` (the natural validation), to ``PATH2``.
- ``{"job": "matmul", "threads": [1, 2], "repeats": 5}``: the fp32 matmul GFLOP/s.
- ``{"job": "profile", "model": ONNX, "threads": [1], "cases": DIR}``: onnxruntime's profiler
  over one call on the first window of the benchmark set: ms by operator type
  (:mod:`spk2img.bench.profile`).
- ``{"job": "stream", "model": ONNX, "mode": "whole"|"reuse", "threads": [1], "spikes": NPY,
  "stride": 7, "outputs": PATH}``: stream the ``(T, H, W)`` spikes through the network at every
  ``stride``-th centre (null: the model's block stride), each window whole or each block
  encoded once (:mod:`spk2img.runtime.block_stream`), after one untimed warm-up call; the wall
  seconds, and the frames saved to ``PATH``.
- ``{"job": "gpu", "model": ONNX, "device": "cuda", "batch": 8, "self_ensemble": false,
  "threads": [1], "repeats": 5, "cases": DIR, "spikes": NPY}``: on a GPU device
  (:mod:`spk2img.bench.gpu`), ``batch`` windows of the benchmark set per call (after two
  untimed calls; with ``self_ensemble``, each with its three mirror images in the same call),
  or with ``batch`` 0 the stream streamed with block reuse: the median ms per frame and the
  provider it ran on.
- ``{"job": "tiers", "model": ONNX, "threads": [1], "cases": DIR, "outputs": DIR}``: each
  ``quality`` tier (:mod:`spk2img.runtime.adaptive`) on every window of the benchmark set, after
  one warm-up call: the seconds of each window, the share of pixels the balanced tier ran the
  network on, and each tier's images saved to ``DIR/<tier>.npy``.

The parent sets ``OMP_NUM_THREADS`` and friends; a process runs one job, so rows never share
caches, allocator pools or a peak RSS.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

from .cases import load_spikes
from .rows import row_from_json
from .timing import call_seconds, matmul_gflops, median_ms


def peak_rss_mib() -> float:
    """This process's peak resident set so far, MiB.

    Linux's ``VmHWM`` (``/proc/self/status``, KiB) is this program's own high-water mark;
    ``ru_maxrss`` would also count the parent's resident set at the ``fork`` that started us
    (Linux carries it across ``exec``), so it is only the fallback elsewhere (KiB on Linux).
    """
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure_row(spec: dict) -> dict:
    """Time, RSS and images of one row (see the module docstring)."""
    row = row_from_json(spec["row"])
    spikes = load_spikes(Path(spec["cases"]))
    window = np.array(spikes[0])
    result: dict = {"ms_per_frame": {}, "seconds": {}, "load_s": {}}
    for threads in spec["threads"]:
        reconstruct = None  # drop the previous session before building the next
        start = time.perf_counter()
        reconstruct = row.build(threads)
        result["load_s"][str(threads)] = time.perf_counter() - start
        seconds, image = call_seconds(partial(reconstruct, window), spec["repeats"], spec["warmup"])
        result["seconds"][str(threads)] = seconds
        result["ms_per_frame"][str(threads)] = median_ms(seconds)
    result["peak_rss_mib"] = peak_rss_mib()
    if spec["score"]:
        images = np.stack([reconstruct(np.array(w)) for w in spikes]).astype(np.float32)
    else:
        images = image[None].astype(np.float32)
    np.save(spec["outputs"], images)
    if spec.get("natural"):
        windows = load_spikes(Path(spec["natural"]))
        natural = np.stack([reconstruct(np.array(w)) for w in windows]).astype(np.float32)
        np.save(spec["natural_outputs"], natural)
    return result


def measure_matmul(spec: dict) -> dict:
    """fp32 matmul GFLOP/s at each thread count of the spec."""
    rates = {str(t): matmul_gflops(t, spec["repeats"]) for t in spec["threads"]}
    return {"gflops": rates}


def measure_stream(spec: dict) -> dict:
    """Seconds to stream a spike file through the network whole or with block reuse."""
    from spk2img.runtime.loader import load_network
    from spk2img.runtime.stream import collect, frame_chunks, run_stream
    from spk2img.runtime.windows import CenterPlan

    (threads,) = spec["threads"]
    spikes = np.load(spec["spikes"], mmap_mode="r")
    height, width = spikes.shape[1:]
    network = load_network(
        spec["model"],
        device=spec.get("device", "cpu"),
        threads=threads,
        block_reuse=spec["mode"] == "reuse",
        warm_up=False,
        memory_arena=True,  # as spk2img.Reconstructor (and the CLI) runs it
    )
    network.warm_up(height, width)
    geometry = network.geometry
    stride = spec.get("stride") or geometry.block_stride
    recon = network.reconstructor(height, width, CenterPlan(geometry.window_frames, stride=stride))
    start = time.perf_counter()
    frames, centers = collect(run_stream(recon, frame_chunks(spikes)), height, width)
    seconds = time.perf_counter() - start
    np.save(spec["outputs"], frames)
    return {
        "seconds": seconds,
        "outputs": len(centers),
        "reconstructor": type(recon).__name__,
        "blocks_encoded": getattr(recon, "blocks_encoded", None),
        "peak_rss_mib": peak_rss_mib(),
    }


def measure_gpu(spec: dict) -> dict:
    """ms per frame of one GPU row: one-shot ``batch`` windows a call, or streamed (0)."""
    import tempfile

    from spk2img.runtime.loader import load_network

    (threads,) = spec["threads"]
    network = load_network(
        spec["model"],
        device=spec["device"],
        threads=threads,
        block_reuse=False,
        warm_up=False,
        self_ensemble=spec["self_ensemble"],
    )
    model = network.predict
    where = {"device": model.device, "provider": model.provider}
    if spec["batch"]:
        windows = load_spikes(Path(spec["cases"]))
        picks = [np.array(windows[i % len(windows)]) for i in range(spec["batch"])]
        batch = np.stack(picks).astype(np.float32)
        seconds, _ = call_seconds(partial(model, batch), spec["repeats"], warmup=2)
        return {**where, "ms_per_frame": median_ms(seconds) / spec["batch"], "seconds": seconds}
    del model  # the stream job loads its own sessions
    with tempfile.TemporaryDirectory(prefix="spk2img-gpu-") as tmp:
        stream = {**spec, "mode": "reuse", "stride": None, "outputs": str(Path(tmp) / "f.npy")}
        result = measure_stream(stream)
    ms = 1000.0 * result["seconds"] / result["outputs"]
    return {
        **where,
        "ms_per_frame": ms,
        "seconds": [result["seconds"]],
        "frames": result["outputs"],
    }


def measure_tiers(spec: dict) -> dict:
    """Seconds and images of each quality tier on every window of the benchmark set."""
    from spk2img.runtime.adaptive import balanced_image
    from spk2img.runtime.loader import load_network
    from spk2img.runtime.stream import tfp_image

    (threads,) = spec["threads"]
    windows = load_spikes(Path(spec["cases"]))
    model = load_network(spec["model"], threads=threads, block_reuse=False, warm_up=False).predict
    shares: list[float] = []

    def balanced(window: np.ndarray) -> np.ndarray:
        image, share = balanced_image(window, model)
        shares.append(share)
        return image

    tiers = {
        "best": lambda window: model(window[None].astype(np.float32))[0],
        "balanced": balanced,
        "fast": lambda window: tfp_image(window.sum(0, dtype=np.int32), len(window)),
    }
    model(np.zeros((1, *windows.shape[1:]), np.float32))  # warm-up
    seconds: dict[str, list[float]] = {tier: [] for tier in tiers}
    images: dict[str, list[np.ndarray]] = {tier: [] for tier in tiers}
    for window in windows:
        window = np.array(window)
        for tier, reconstruct in tiers.items():
            start = time.perf_counter()
            images[tier].append(reconstruct(window))
            seconds[tier].append(time.perf_counter() - start)
    for tier, stack in images.items():
        np.save(Path(spec["outputs"]) / f"{tier}.npy", np.stack(stack).astype(np.float32))
    return {"seconds": seconds, "balanced_share": shares, "peak_rss_mib": peak_rss_mib()}


def measure_profile(spec: dict) -> dict:
    from .profile import operator_times

    window = np.asarray(load_spikes(Path(spec["cases"]))[0:1], np.float32)
    return operator_times(spec["model"], window, max(spec["threads"]))


JOBS = {
    "row": measure_row,
    "profile": measure_profile,
    "matmul": measure_matmul,
    "stream": measure_stream,
    "tiers": measure_tiers,
    "gpu": measure_gpu,
}


class WorkerError(RuntimeError):
    """A worker process failed; the message ends with its last lines of stderr."""


def thread_env(threads: int) -> dict[str, str]:
    """Environment variables that cap the math libraries' thread pools at ``threads``."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    return {name: str(threads) for name in names}


def run_job(spec: dict, timeout_s: float | None = None) -> dict:
    """Run ``spec`` in a fresh ``python -m spk2img.bench.worker`` with the thread pools capped at
    its largest thread count; its result (raises :class:`WorkerError`)."""
    env = {**os.environ, **thread_env(max(spec["threads"]))}
    cmd = [sys.executable, "-m", "spk2img.bench.worker", json.dumps(spec)]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s)
    except subprocess.TimeoutExpired as exc:
        raise WorkerError(f"no result after {timeout_s:.0f} s") from exc
    if done.returncode != 0:
        tail = " | ".join(done.stderr.strip().splitlines()[-3:])
        raise WorkerError(f"exit code {done.returncode}: {tail}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str]) -> int:
    spec = json.loads(argv[0])
    print(json.dumps(JOBS[spec["job"]](spec)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
