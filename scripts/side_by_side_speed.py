"""Time ONNX graphs side by side: one 250x400 frame each, interleaved, at 1 and 2 threads, then
the stride-7 stream cost per output with block reuse of those with block graphs beside them.

``python scripts/side_by_side_speed.py NAME=GRAPH.onnx [NAME=GRAPH.onnx …] [--out FILE.json]``

A quick comparison for model work (the matmul rate of the same run included); the bench
(`spk2img bench`) is the full account, each row in its own process and scored.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from spk2img.bench.streaming import stream_benchmark
from spk2img.bench.timing import matmul_gflops
from spk2img.runtime.block_codec import block_graph_paths
from spk2img.runtime.onnx_backend import session_options

HEIGHT, WIDTH, REPEATS, STREAM_FRAMES = 250, 400, 7, 300


def session(path: str, threads: int) -> ort.InferenceSession:
    options = session_options(threads, memory_arena=True)  # as the CLI's and the API's
    return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])


def frame_ms(graphs: dict[str, str], threads: int) -> dict[str, float]:
    """Median ms of one frame per graph, the graphs' calls interleaved (two warm-ups each)."""
    window = np.random.default_rng(0).random((1, 41, HEIGHT, WIDTH)) < 0.3
    feed = {"spikes": window.astype(np.float32)}
    sessions = {name: session(path, threads) for name, path in graphs.items()}
    for run in sessions.values():
        for _ in range(2):
            run.run(None, feed)
    seconds: dict[str, list[float]] = {name: [] for name in graphs}
    for _ in range(REPEATS):
        for name, run in sessions.items():
            start = time.perf_counter()
            run.run(None, feed)
            seconds[name].append(time.perf_counter() - start)
    return {name: 1000 * statistics.median(s) for name, s in seconds.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("graphs", nargs="+", help="NAME=GRAPH.onnx")
    parser.add_argument("--out", type=Path, help="also write the figures to this JSON file")
    args = parser.parse_args()
    graphs = dict(item.split("=", 1) for item in args.graphs)
    result = {"matmul_gflops": {t: matmul_gflops(t, REPEATS) for t in (1, 2)}, "graphs": {}}
    for threads in (1, 2):
        for name, ms in frame_ms(graphs, threads).items():
            result["graphs"].setdefault(name, {})[f"ms_{threads}_threads"] = ms
    for name, path in graphs.items():
        if all(p.is_file() for p in block_graph_paths(path).values()):
            with tempfile.TemporaryDirectory() as work:
                stream = stream_benchmark(
                    Path(path), STREAM_FRAMES, HEIGHT, WIDTH, (2,), Path(work), lambda _: None
                )
            row = stream["rows"][0]
            result["graphs"][name]["stream_ms_per_output_2_threads"] = {
                mode: 1000 * row[mode]["seconds"] / row[mode]["outputs"]
                for mode in ("whole", "reuse")
            }
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
