"""Measure one benchmark job in this (fresh) process and print the result as one JSON line.

``python -m spk2img.bench.worker '<json spec>'`` with a spec of one of two jobs:

- ``{"job": "row", "row": ROW, "threads": [1, 2], "repeats": 5, "warmup": 1, "cases": DIR,
  "score": false, "outputs": PATH}``: build the row (:func:`~spk2img.bench.rows.row_from_json`)
  at each thread count, time it on the first window of the benchmark set in ``DIR``, note the
  peak RSS, then save to ``PATH`` (``.npy``) its images of every window (``score``) or of the
  timed window only: ``(N, H, W) float32``.
- ``{"job": "matmul", "threads": [1, 2], "repeats": 5}``: the fp32 matmul GFLOP/s.

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
    return result


def measure_matmul(spec: dict) -> dict:
    """fp32 matmul GFLOP/s at each thread count of the spec."""
    rates = {str(t): matmul_gflops(t, spec["repeats"]) for t in spec["threads"]}
    return {"gflops": rates}


JOBS = {"row": measure_row, "matmul": measure_matmul}


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
