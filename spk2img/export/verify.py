"""Torch vs onnxruntime parity of an exported graph (the check ``export`` ends with and
``verify`` runs in full).

For each :class:`~spk2img.export.hard_cases.Case` the PyTorch network and the ONNX graph run on
the same windows; their ``(B, H, W)`` outputs are compared by

- ``max_abs``: ``max |onnx - torch|`` (linear intensity units),
- ``max_rel``: ``max |onnx - torch| / max(|torch|, 1e-3)`` (the floor keeps black pixels from
  dividing by zero),
- ``psnr_db``: PSNR of the onnx output against the torch output, peak 1 (``inf``: identical),
- ``nonfinite``: NaN or Inf values in either output.

A case passes when ``max_abs <= atol`` and ``nonfinite == 0``. A reduced-precision graph
(``fp16``, ``int8``: its metadata says which, or ``verify --fp16`` converts the fp32 graph, the
GPU's precision, docs/gpu.md) cannot hold float32's ``atol``: its cases pass when
``psnr_db >= MIN_PSNR_VS_FP32`` (30 dB, the bar ``export`` sets such graphs against fp32) and
``nonfinite == 0``, and every case reports its errors all the same. ``device`` runs the
onnxruntime side on a GPU (:func:`spk2img.runtime.loader.load_network`).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from google.protobuf.message import DecodeError

from spk2img.errors import InputError
from spk2img.evaluation.metrics import psnr
from spk2img.model.network import Spk2ImgNet
from spk2img.runtime.loader import load_network

from .block_graphs import stream_block_graphs, whole_windows
from .hard_cases import Case, far_offset_copy
from .metadata import weights_sha256
from .onnx_export import (
    ExportConfig,
    ExportSource,
    checkpoint_source,
    export_onnx,
    graph_kind,
    graph_props,
    random_source,
    weight_arrays,
    write_weights,
)
from .quantize import MIN_PSNR_VS_FP32, reduce_block_graphs, reduce_precision

ATOL = 1e-4
"""Largest fp32 difference allowed between torch and onnxruntime (linear intensity)."""
REL_FLOOR = 1e-3


@dataclass(frozen=True)
class CaseResult:
    """One case run with one onnxruntime thread count."""

    case: str
    shape: tuple[int, ...]
    threads: int
    max_abs: float
    max_rel: float
    psnr_db: float
    nonfinite: int
    torch_s: float
    onnx_s: float
    passed: bool
    precision: str = "fp32"
    """The graph's precision: ``fp32``, ``fp16`` or ``int8``."""
    device: str = "cpu"
    """Where onnxruntime ran it (:data:`~spk2img.runtime.onnx_backend.DEVICES`, concrete)."""


def case_passes(scores: dict, precision: str, atol: float) -> bool:
    """fp32: ``max_abs <= atol``; fp16/int8: ``psnr_db >= MIN_PSNR_VS_FP32``; never NaN/Inf."""
    if scores["nonfinite"]:
        return False
    if precision == "fp32":
        return bool(scores["max_abs"] <= atol)
    return bool(scores["psnr_db"] >= MIN_PSNR_VS_FP32)


@dataclass(frozen=True)
class VerifyReport:
    model: str
    atol: float
    results: list[CaseResult]

    @property
    def passed(self) -> bool:
        return all(r.passed for r in self.results)

    def table(self) -> str:
        """The results as a fixed-width text table."""
        head = (
            f"{'case':<30} {'input (B,T,H,W)':<18} {'prec':<4} {'dev':<4} {'thr':>3} "
            f"{'max abs':>9} {'max rel':>9} {'PSNR dB':>8} {'NaN/Inf':>7} {'torch s':>8} "
            f"{'onnx s':>7}  ok"
        )
        rows = [head, "-" * len(head)]
        for r in self.results:
            shape = "x".join(str(d) for d in r.shape)
            rows.append(
                f"{r.case:<30} {shape:<18} {r.precision:<4} {r.device[:4]:<4} {r.threads:>3} "
                f"{r.max_abs:>9.2e} {r.max_rel:>9.2e} {r.psnr_db:>8.1f} {r.nonfinite:>7} "
                f"{r.torch_s:>8.2f} {r.onnx_s:>7.2f}  {'yes' if r.passed else 'NO'}"
            )
        verdict = "PASS" if self.passed else "FAIL"
        rule = f"{verdict}: max abs error <= {self.atol:g} (fp32)"
        if any(r.precision != "fp32" for r in self.results):
            rule += f", PSNR against torch >= {MIN_PSNR_VS_FP32:g} dB (fp16/int8)"
        rows.append(rule + " and no NaN/Inf required")
        return "\n".join(rows)

    def to_json(self) -> dict:
        """A JSON-ready dict; an infinite PSNR (identical outputs) is written as ``null``."""
        results = [
            {**asdict(r), "psnr_db": r.psnr_db if math.isfinite(r.psnr_db) else None}
            for r in self.results
        ]
        return {"model": self.model, "atol": self.atol, "passed": self.passed, "results": results}


def compare_outputs(reference: np.ndarray, candidate: np.ndarray) -> dict[str, float | int]:
    """``max_abs``, ``max_rel``, ``psnr_db`` and ``nonfinite`` of two same-shape outputs."""
    nonfinite = int((~np.isfinite(reference)).sum() + (~np.isfinite(candidate)).sum())
    diff = np.abs(candidate.astype(np.float64) - reference.astype(np.float64))
    if nonfinite:
        return {
            "max_abs": math.inf,
            "max_rel": math.inf,
            "psnr_db": -math.inf,
            "nonfinite": nonfinite,
        }
    return {
        "max_abs": float(diff.max()),
        "max_rel": float((diff / np.maximum(np.abs(reference), REL_FLOOR)).max()),
        "psnr_db": psnr(candidate, reference),
        "nonfinite": 0,
    }


def reference_model(onnx_path: str | Path, checkpoint: str | Path | None = None) -> Spk2ImgNet:
    """The PyTorch network an ONNX graph was exported from, checked by its weights' SHA-256.

    The weights come from ``checkpoint``, else from the checkpoint next to the graph (same
    stem, ``.pt``), else, for a graph exported with random weights, from the member and seed in
    its metadata. An ONNX file holds no PyTorch code, so one of these must exist.
    """
    onnx_path = Path(onnx_path)
    try:
        graph = onnx.load(onnx_path)
    except DecodeError as exc:
        raise InputError(f"{onnx_path}: not an ONNX model ({exc})") from None
    metadata = graph_props(graph)
    beside = onnx_path.with_suffix(".pt")
    if checkpoint is None and beside.is_file():
        checkpoint = beside
    if checkpoint is not None:
        model = checkpoint_source(checkpoint).model
    elif "random_seed" in metadata and "member" in metadata:
        model = random_source(metadata["member"], int(metadata["random_seed"])).model
    else:
        raise InputError(
            f"{onnx_path}: no weights to compare with; pass --checkpoint CKPT or put the "
            f"checkpoint next to the model as {beside.name}"
        )
    expected = metadata.get("weights_sha256")
    if expected and weights_sha256(model.state_dict()) != expected:
        raise InputError(
            f"{checkpoint}: its weights are not the ones {onnx_path.name} was exported from "
            "(weights_sha256 differs)"
        )
    return model.eval()


def verify_onnx(
    onnx_path: str | Path,
    model: Spk2ImgNet,
    cases: list[Case],
    atol: float = ATOL,
    progress: Callable[[CaseResult], None] | None = None,
    fp16: bool = False,
    device: str = "cpu",
) -> VerifyReport:
    """Run ``model`` (the exported network, eval mode) and the graph at ``onnx_path`` on every
    case and compare their outputs; ``progress`` is called with each result as it comes.

    Cases with a ``variant`` run a modified copy of ``model`` against the same graph with the
    copy's weights (an fp32 graph's changed weights rewritten; any other graph exported afresh
    from the copy the same way: same graph kind, and precision) in a temporary directory. With
    ``fp16`` (an fp32 graph only) every case also runs the graph converted to fp16
    (:func:`~spk2img.export.quantize.reduce_precision`). ``device``: where onnxruntime runs;
    off the CPU and for reduced precision only the case's first thread count runs.
    """
    onnx_path = Path(onnx_path)
    graph = onnx.load(onnx_path, load_external_data=False)
    kind, own = graph_kind(graph), graph_precision(graph)
    if fp16 and own != "fp32":
        raise InputError(f"--fp16 converts an fp32 graph; {onnx_path.name} is {own} already")
    precisions = [own, "fp16"] if fp16 else [own]
    results = []
    with tempfile.TemporaryDirectory(prefix="spk2img-verify-") as tmp:
        variants = {None: (model.eval(), onnx_path)}
        graphs = {(None, own): onnx_path}

        def graph_for(variant: str | None, precision: str) -> Path:
            if (variant, precision) not in graphs:
                path = Path(tmp) / f"{len(graphs)}-{precision}.onnx"
                reduce_precision(variants[variant][1], path, precision)
                graphs[variant, precision] = path
            return graphs[variant, precision]

        for case in cases:
            if case.variant not in variants:
                variants[case.variant] = _variant_graph(
                    model, case.variant, onnx_path, kind, own, Path(tmp)
                )
                graphs[case.variant, "fp32"] = variants[case.variant][1]
            net = variants[case.variant][0]
            spikes = np.ascontiguousarray(net.config.geometry.crop(case.spikes, axis=1))
            start = time.perf_counter()
            with torch.inference_mode():
                reference = net(torch.from_numpy(spikes))[0][:, 0].numpy()
            torch_s = time.perf_counter() - start
            for precision in precisions:
                path = graph_for(case.variant, precision)
                counts = (
                    case.threads if precision == "fp32" and device == "cpu" else case.threads[:1]
                )
                for threads in counts:
                    graph = load_network(
                        path, device=device, threads=threads, block_reuse=False, warm_up=False
                    ).predict  # the graph as the runtime loads it, on this case alone
                    start = time.perf_counter()
                    output = graph(spikes)
                    onnx_s = time.perf_counter() - start
                    where = graph.device
                    del graph
                    scores = compare_outputs(reference, output)
                    result = CaseResult(
                        case.name,
                        spikes.shape,
                        threads,
                        **scores,
                        torch_s=torch_s,
                        onnx_s=onnx_s,
                        passed=case_passes(scores, precision, atol),
                        precision=precision,
                        device=where,
                    )
                    results.append(result)
                    if progress:
                        progress(result)
    return VerifyReport(str(onnx_path), atol, results)


def graph_precision(graph: onnx.ModelProto) -> str:
    """The ``precision`` of a graph's metadata (``fp32`` when it has none)."""
    return graph_props(graph).get("precision", "fp32")


def verify_block_graphs(
    onnx_path: str | Path,
    model: Spk2ImgNet,
    spikes: np.ndarray,
    name: str,
    atol: float = ATOL,
    fp16: bool = False,
    device: str = "cpu",
) -> CaseResult:
    """The block encoder and head beside ``onnx_path`` streamed at their block stride over
    ``spikes`` ``(T, H, W)`` with block reuse, against ``model`` on each window whole (one thread).
    ``fp16``: the fp16 conversions of both graphs instead; ``device``: where they run."""
    graph = onnx.load(onnx_path, load_external_data=False)
    precision = "fp16" if fp16 else graph_precision(graph)
    with tempfile.TemporaryDirectory(prefix="spk2img-verify-") as tmp:
        if fp16:
            converted = Path(tmp) / "fp16.onnx"
            reduce_block_graphs(onnx_path, converted, "fp16")
            onnx_path = converted
        start = time.perf_counter()
        streamed, centers, ran_on = stream_block_graphs(onnx_path, spikes, device)
        onnx_s = time.perf_counter() - start
    start = time.perf_counter()
    reference = whole_windows(model, spikes, centers)
    torch_s = time.perf_counter() - start
    scores = compare_outputs(reference, streamed)
    shape = (len(reference), model.config.window_frames, *spikes.shape[1:])
    ok = case_passes(scores, precision, atol)
    return CaseResult(
        name,
        shape,
        1,
        **scores,
        torch_s=torch_s,
        onnx_s=onnx_s,
        passed=ok,
        precision=precision,
        device=ran_on,
    )


def _variant_graph(
    model: Spk2ImgNet, variant: str, onnx_path: Path, kind: str, precision: str, directory: Path
) -> tuple[Spk2ImgNet, Path]:
    """The network ``variant`` of ``model`` and its graph in ``directory``: the graph under test
    (of graph kind ``kind`` and ``precision``), if fp32, with the variant's weights
    written over its own (:func:`~spk2img.export.onnx_export.write_weights`); any other
    exported afresh."""
    if variant != "far offsets":
        raise ValueError(f"unknown model variant {variant!r}")
    far = far_offset_copy(model)
    path = directory / "far-offsets.onnx"
    own, new = weight_arrays(model.state_dict()), weight_arrays(far.state_dict())
    changed = {name for name in own if not np.array_equal(own[name], new[name])}
    graph = onnx.load(onnx_path) if precision == "fp32" else None
    written = write_weights(graph, own, new) if graph is not None else None
    if written is not None and changed <= written:
        props = {k: v for k, v in graph_props(graph).items() if k != "weights_sha256"}
        del graph.metadata_props[:]
        onnx.helper.set_model_props(graph, props | {"name": "far-offsets variant"})
        onnx.save_model(graph, path)
    else:
        source = ExportSource(far, {"name": "far-offsets variant"})
        export_onnx(source, path, ExportConfig(graph=kind))
    return far, path
