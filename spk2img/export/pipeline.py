"""Export followed by validation: the one function ``spk2img export``, the tests and CI call.

1. Trace the network to fp32 ONNX (:func:`~spk2img.export.onnx_export.export_onnx`) and, for
   fp32 unless asked not to, to the block encoder and the align-and-fuse head
   (:mod:`~spk2img.export.block_graphs`). Where a shipped model has the same architecture,
   its traced graphs take the network's weights instead (:mod:`~spk2img.export.reuse`: seconds
   instead of minutes), and are traced after all if they fail a check of step 2.
2. Check torch/onnxruntime parity on the smoke cases (:func:`~spk2img.export.hard_cases.
   smoke_cases`: the example size with batch 2, and 17x23) against ``atol``; the block graphs,
   streamed with block reuse, against the PyTorch one-shot network
   (:func:`~spk2img.export.block_graphs.block_parity`, to ``atol``).
3. For ``fp16``/``int8``, convert, and measure the variant against the fp32 graph and the
   ground truth on the validation set (:func:`~spk2img.export.quantize.precision_report`);
   the report is stored in the metadata as ``precision_report`` (JSON).

Nothing is written to ``out`` unless every check passes.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import onnx

from spk2img.runtime.block_codec import block_graph_paths

from .block_graphs import block_parity, export_block_graphs
from .hard_cases import smoke_cases
from .onnx_export import ExportConfig, ExportError, ExportSource, export_onnx, graph_props
from .quantize import MIN_PSNR_VS_FP32, PRECISIONS, precision_report, reduce_precision
from .reuse import find_template, reuse_graphs
from .verify import ATOL, CaseResult, VerifyReport, verify_onnx


@dataclass(frozen=True)
class ExportResult:
    path: Path
    parity: VerifyReport
    """fp32 torch/onnxruntime parity on the smoke cases."""
    precision: dict | None
    """:func:`~spk2img.export.quantize.precision_report` of a fp16/int8 variant, else None."""
    block_parity: float | None = None
    """Largest difference of the block graphs, streamed, from torch's one-shot output (None:
    no block graphs were written)."""
    reused: Path | None = None
    """The shipped graph whose trace (same architecture) took these weights, or None: traced
    (:mod:`~spk2img.export.reuse`)."""


def export_verified(
    source: ExportSource,
    out: str | Path,
    config: ExportConfig | None = None,
    precision: str = "fp32",
    atol: float = ATOL,
    progress: Callable[[CaseResult], None] | None = None,
    block_graphs: bool = True,
    reuse: bool = True,
) -> ExportResult:
    """Export ``source`` to ``out`` at ``precision`` and validate it (see the module doc;
    ``config`` None: the default :class:`ExportConfig`; ``block_graphs``: also write the fp32
    encoder and head beside ``out``; ``reuse``: start from a shipped model's traced graphs where
    one has the same architecture);
    raises :class:`~spk2img.export.onnx_export.ExportError` if a check fails."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    config = config or ExportConfig()
    block_graphs = block_graphs and precision == "fp32"
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".spk2img-export-", dir=out.parent) as tmp:
        fp32_path = Path(tmp) / "fp32.onnx"
        template = find_template(source, config, block_graphs) if reuse else None
        checked = None
        try:
            if template is not None and reuse_graphs(
                template, source, fp32_path, config, block_graphs
            ):
                checked = check_fp32(source, fp32_path, config, atol, progress, block_graphs)
        except ExportError:
            pass  # the reused graphs fail a check that a trace must pass: trace
        if checked is None:
            template = None
            export_onnx(source, fp32_path, config)
            if block_graphs:
                export_block_graphs(source, fp32_path, config)
            checked = check_fp32(source, fp32_path, config, atol, progress, block_graphs)
        parity, parts_error = checked
        report = None
        final = fp32_path
        if precision != "fp32":
            final = Path(tmp) / f"{precision}.onnx"
            model = reduce_precision(fp32_path, final, precision)
            report = precision_report(fp32_path, final)
            if report["nonfinite"] or not report["psnr_vs_fp32_db"] >= MIN_PSNR_VS_FP32:
                raise ExportError(f"the {precision} graph is too far from fp32: {report}")
            onnx.helper.set_model_props(
                model,
                graph_props(model) | {"precision_report": json.dumps(report, sort_keys=True)},
            )
            onnx.save_model(model, final, save_as_external_data=False)
        if block_graphs:
            for part, path in block_graph_paths(fp32_path).items():
                shutil.move(path, block_graph_paths(out)[part])
        shutil.move(final, out)
    return ExportResult(out, parity, report, parts_error, template)


def check_fp32(
    source: ExportSource,
    fp32_path: Path,
    config: ExportConfig,
    atol: float,
    progress: Callable[[CaseResult], None] | None,
    block_graphs: bool,
) -> tuple[VerifyReport, float | None]:
    """The fp32 graph at ``fp32_path`` (and its block graphs, if ``block_graphs``) against
    ``source``'s network in PyTorch: the smoke cases' parity report and the block graphs'
    largest difference (None without them); raises
    :class:`~spk2img.export.onnx_export.ExportError` where either is over ``atol``."""
    cases = smoke_cases(config.example_height, config.example_width)
    parity = verify_onnx(fp32_path, source.model, cases, atol, progress)
    if not parity.passed:
        raise ExportError(f"torch/onnxruntime parity failed:\n{parity.table()}")
    if not block_graphs:
        return parity, None
    parts_error = block_parity(fp32_path, source.model)
    if not parts_error <= atol:
        raise ExportError(
            f"the block encoder and head differ from torch by {parts_error:.3g} > {atol}"
        )
    return parity, parts_error
