"""Where a graph's time goes: onnxruntime's profiler over one call, summed per operator type.

:func:`operator_times` runs a graph twice on one window with profiling on and reads the trace
(Chrome trace JSON) of the second run: the ``Node`` kernel events inside its ``model_run``,
their durations summed by ``op_name`` (Conv, DeformConv, GridSample, ReorderInput …).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

TOP_OPERATORS = 5
"""Operator types a report names per graph; the rest are summed as ``other``."""


def operator_times(model: str | Path, window: np.ndarray, threads: int) -> dict:
    """``{"run_ms": the profiled call's ms, "ops": {op type: ms}}`` of ``model`` on ``window``
    (``(1, F, H, W) float32``, cropped to the graph's frames) with ``threads`` intra-op
    threads, the second of two calls."""
    import onnxruntime as ort

    from spk2img.runtime.onnx_backend import graph_geometry, session_options

    options = session_options(threads)
    options.enable_profiling = True
    with tempfile.TemporaryDirectory(prefix="spk2img-profile-") as tmp:
        options.profile_file_prefix = os.path.join(tmp, "trace")
        session = ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])
        graph_input = session.get_inputs()[0]
        metadata = session.get_modelmeta().custom_metadata_map
        window = graph_geometry(metadata, graph_input.shape).crop(window, axis=1)
        feeds = {graph_input.name: np.ascontiguousarray(window, np.float32)}
        session.run(None, feeds)
        session.run(None, feeds)
        events = json.loads(Path(session.end_profiling()).read_text())
    return summarise(events)


def summarise(events: list[dict]) -> dict:
    """The last ``model_run`` of a trace: its ms and its kernels' ms by operator type."""
    run = [e for e in events if e.get("name") == "model_run"][-1]
    start, stop = run["ts"], run["ts"] + run["dur"]
    ops: dict[str, float] = defaultdict(float)
    for event in events:
        if event.get("cat") != "Node" or not event["name"].endswith("_kernel_time"):
            continue
        if start <= event["ts"] < stop:
            ops[event["args"]["op_name"]] += event["dur"] / 1000
    return {"run_ms": run["dur"] / 1000, "ops": dict(sorted(ops.items(), key=lambda kv: -kv[1]))}


def top_operators(ops: dict[str, float], count: int = TOP_OPERATORS) -> list[tuple[str, float]]:
    """The ``count`` costliest operator types and ``other``, as shares of the kernels' time."""
    total = sum(ops.values()) or 1.0
    ranked = sorted(ops.items(), key=lambda kv: -kv[1])
    shares = [(name, ms / total) for name, ms in ranked[:count]]
    rest = sum(ms for _, ms in ranked[count:]) / total
    return shares + ([("other", rest)] if rest > 0 else [])
