"""``spk2img verify``: torch vs onnxruntime parity of an exported graph on simulated scenes and
hard cases (needs the export extra)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from spk2img.cli.arguments import check_output_file, thread_count
from spk2img.errors import InputError
from spk2img.io.spikes import MAX_SIDE, check_size
from spk2img.runtime.onnx_backend import DEVICES


def parse_size(text: str) -> tuple[int, int]:
    """``"250x400"`` -> ``(250, 400)``."""
    try:
        height, width = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise InputError(f"a size is HEIGHTxWIDTH, e.g. 250x400, got {text!r}") from None
    check_size(height, width, MAX_SIDE)
    return height, width


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "verify",
        help="check an exported ONNX model against its PyTorch network",
        description="Run the PyTorch network and the ONNX graph on simulated scenes and hard "
        "cases (dark, saturated, single spike, flicker, fast motion, far offsets, odd and large "
        "sizes, 1 and 2 onnxruntime threads); print max abs/rel error, PSNR and NaN/Inf per case; "
        "exit 1 if any case exceeds --atol or is not finite. With MODEL.encoder.onnx and "
        "MODEL.head.onnx beside it, also stream them with block reuse at stride 7 against the "
        "network on each window. The weights come from --checkpoint, "
        "else MODEL.pt next to MODEL.onnx, else (random-weight exports) the metadata's seed. "
        "A fp16/int8 graph, and --fp16's conversion, pass a case at PSNR >= 30 dB against "
        "PyTorch with no NaN/Inf.",
    )
    p.add_argument("model", type=Path, help="the exported .onnx")
    p.add_argument("--checkpoint", type=Path, help="the checkpoint it was exported from")
    p.add_argument("--json", type=Path, help="also write the results as JSON here")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument(
        "--quick", action="store_true", help="scenes up to 250x250 only, no 250x400 stream (CI)"
    )
    scale.add_argument(
        "--full",
        action="store_true",
        help="also a 1000x1000 scene (about 12 GB of peak memory; the default stops at 250x400)",
    )
    p.add_argument(
        "--sizes", help="comma-separated HxW scene sizes instead of the default list, e.g. 17x23"
    )
    p.add_argument("--atol", type=float, default=None, help="max abs error allowed (1e-4)")
    p.add_argument(
        "--threads", type=thread_count, default=None, help="PyTorch threads for the reference"
    )
    p.add_argument(
        "--fp16",
        action="store_true",
        help="also convert the graph (and its block graphs) to fp16, the GPU's precision, and "
        "report its error on every case",
    )
    p.add_argument(
        "--device",
        choices=DEVICES,
        default="cpu",
        help="where onnxruntime runs the graphs (default cpu; docs/gpu.md)",
    )


def run(args: argparse.Namespace) -> int:
    import torch  # the export extra (spk2img.cli.extras checked it is there)

    from spk2img.export import hard_cases
    from spk2img.export.hard_cases import CASE_HEIGHT, CASE_WIDTH
    from spk2img.export.verify import (
        ATOL,
        VerifyReport,
        reference_model,
        verify_block_graphs,
        verify_onnx,
    )
    from spk2img.runtime.allocator import map_large_allocations_apart
    from spk2img.runtime.block_codec import block_graph_paths

    if args.json:
        check_output_file(args.json, "--json")
    if args.atol is not None and not 0 <= args.atol < math.inf:
        raise InputError(f"--atol {args.atol}: must be a number >= 0")
    if args.sizes is not None and not args.sizes.replace(",", "").strip():
        raise InputError(f"--sizes {args.sizes!r}: name at least one HEIGHTxWIDTH")
    # each case's torch and onnxruntime buffers go back to the system when freed, so the peak
    # is the largest case's, not the sum of the heaps left behind (2.50 -> 2.15 GB for default)
    map_large_allocations_apart()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = reference_model(args.model, args.checkpoint)
    if args.sizes:
        sizes = tuple(parse_size(s) for s in args.sizes.split(",") if s.strip())
        cases = hard_cases.scene_cases() + hard_cases.content_cases() + hard_cases.size_cases(sizes)
    else:
        scene_sizes = hard_cases.DEFAULT_SIZES
        if args.quick or args.full:
            scene_sizes = hard_cases.QUICK_SIZES if args.quick else hard_cases.FULL_SIZES
        cases = hard_cases.standard_cases(scene_sizes)

    def progress(result) -> None:
        print(
            f"  {result.case} ({result.precision}, {result.device}, {result.threads} thr): "
            f"max abs {result.max_abs:.2e}",
            file=sys.stderr,
            flush=True,
        )

    atol = ATOL if args.atol is None else args.atol
    report = verify_onnx(args.model, model, cases, atol, progress, args.fp16, args.device)
    if all(path.is_file() for path in block_graph_paths(args.model).values()):
        sizes = [(CASE_HEIGHT, CASE_WIDTH)] + ([] if args.quick else [(250, 400)])
        streamed = [
            verify_block_graphs(
                args.model,
                model,
                hard_cases.fast_stream(h, w),
                f"block graphs, stream {h}x{w}",
                atol,
                fp16,
                args.device,
            )
            for fp16 in ([False, True] if args.fp16 else [False])
            for h, w in sizes
        ]
        for result in streamed:
            progress(result)
        report = VerifyReport(report.model, report.atol, report.results + streamed)
    print(report.table())
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.to_json(), indent=2) + "\n")
    return 0 if report.passed else 1
