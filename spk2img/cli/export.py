"""``spk2img export``: a checkpoint (or a member with random weights) -> one ONNX file, checked
against PyTorch before it is written (needs the export extra)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from spk2img.cli.arguments import thread_count
from spk2img.cli.verify import parse_size
from spk2img.errors import InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a checkpoint to ONNX and check it against PyTorch",
        description="Export a training checkpoint (or --member with --random-weights) to a "
        "single ONNX file: input 'spikes' (B, 41, H, W) float32 0/1, output 'image' "
        "(B, 1, H, W) linear intensity in [0, 1], dynamic B/H/W, standard operators only, "
        "with metadata (config, version, weights' SHA-256 ...). The export is checked against "
        "PyTorch (max abs error <= 1e-4) before the file is written; 'spk2img verify' runs the "
        "full set of hard cases.",
    )
    p.add_argument("checkpoint", type=Path, nargs="?", help="training checkpoint (.pt)")
    p.add_argument("--out", type=Path, required=True, help="the .onnx to write")
    p.add_argument("--random-weights", action="store_true", help="export --member, untrained")
    p.add_argument("--member", help="family member for --random-weights (paper, small, tiny)")
    p.add_argument("--seed", type=int, default=0, help="seed of --random-weights (default 0)")
    p.add_argument(
        "--deform-conv",
        action="store_true",
        help="express the deformable convs as ONNX DeformConv (opset 19) instead of GridSample",
    )
    p.add_argument(
        "--precision", choices=("fp32", "fp16", "int8"), default="fp32", help="default: fp32"
    )
    p.add_argument(
        "--no-block-graphs",
        action="store_true",
        help="do not also write OUT.encoder.onnx and OUT.head.onnx (the block encoder and the "
        "align-and-fuse head that streams use to encode each block once; fp32 only)",
    )
    p.add_argument(
        "--trace",
        action="store_true",
        help="trace the network even where a shipped model's graphs have its architecture (by "
        "default those take its weights: seconds instead of a minute or more, checked the same)",
    )
    p.add_argument("--name", help="metadata name (default spk2img-<member>)")
    p.add_argument(
        "--example-size", default="24x32", help="HxW the network is traced at (default 24x32)"
    )
    p.add_argument("--threads", type=thread_count, default=None, help="PyTorch threads")


def run(args: argparse.Namespace) -> int:
    if args.random_weights == (args.checkpoint is not None):
        raise InputError("give either a CHECKPOINT or --random-weights --member NAME")
    if args.random_weights and not args.member:
        raise InputError("--random-weights needs --member (paper, small or tiny)")
    if args.member and not args.random_weights:
        raise InputError("--member is for --random-weights; a checkpoint names its own member")
    if args.out.suffix != ".onnx":
        raise InputError(f"--out must name a .onnx file, got {args.out}")
    height, width = parse_size(args.example_size)
    import torch  # the export extra (spk2img.cli.extras checked it is there)

    from spk2img.export.onnx_export import (
        ExportConfig,
        ExportError,
        checkpoint_source,
        operator_counts,
        random_source,
    )
    from spk2img.export.pipeline import export_verified

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.random_weights:
        source = random_source(args.member, args.seed, args.name)
    else:
        source = checkpoint_source(args.checkpoint, args.name)
    graph = "deform_conv" if args.deform_conv else "grid_sample"
    config = ExportConfig(graph=graph, example_height=height, example_width=width)
    try:
        result = export_verified(
            source,
            args.out,
            config,
            args.precision,
            block_graphs=not args.no_block_graphs,
            reuse=not args.trace,
        )
    except ExportError as exc:
        print(f"spk2img export: error: {exc}", file=sys.stderr)
        return 1
    if result.reused is None:
        print("graphs: traced")
    else:
        print(f"graphs: {result.reused.name}'s trace (same architecture) with these weights")
    print(result.parity.table())
    if result.precision:
        print(f"{args.precision} vs fp32 and ground truth: {json.dumps(result.precision)}")
    import onnx

    ops = operator_counts(onnx.load(result.path))
    print("operators: " + ", ".join(f"{op} x{n}" for (_, op), n in sorted(ops.items())))
    print(f"wrote {result.path} ({source.metadata['name']}, {graph}, {args.precision})")
    if result.block_parity is not None:
        print(
            f"wrote {args.out.with_suffix('.encoder.onnx')} and "
            f"{args.out.with_suffix('.head.onnx')} (streamed with block reuse: max abs "
            f"{result.block_parity:.2e} from torch)"
        )
    return 0
