"""``spk2img models``: the Spk2ImgNet family members, their parameters and cost per frame, and
the trained models this installation ships (``--model NAME`` of reconstruct and serve)."""

from __future__ import annotations

import argparse

from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, MAX_SIDE, check_size


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "models",
        help="list the network family (parameters, G MACs per frame) and the shipped models",
        description="List the Spk2ImgNet family members with their parameter counts and "
        "multiply-accumulates (MACs) per frame of the given size (GFLOPs = 2 x G MACs), then "
        "the trained models shipped with spk2img: the names --model takes.",
    )
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width")


def run(args: argparse.Namespace) -> int:
    check_size(args.height, args.width, MAX_SIDE)
    import torch

    from spk2img.model.complexity import count_macs, count_parameters, count_stream_macs
    from spk2img.model.config import MEMBERS
    from spk2img.model.network import build_model

    size = f"G MACs/{args.height}x{args.width}"
    print(f"{'member':<8} {'parameters':>12} {size:>18} {'block reuse':>14} {'ratio':>6}")
    for name, config in MEMBERS.items():
        with torch.device("meta"):
            params = count_parameters(build_model(config))
        macs = count_macs(config, args.height, args.width)
        reuse = sum(count_stream_macs(config, args.height, args.width))
        print(
            f"{name:<8} {params:>12,} {macs / 1e9:>18.1f} {reuse / 1e9:>14.1f} {reuse / macs:>6.2f}"
        )
    print("MACs count weight multiply-accumulates of the convolutions; GFLOPs = 2 x G MACs.")
    print(
        "block reuse: G MACs per output of a stream with centres 7 frames apart that encodes "
        "each 13-frame block once (one block encoded + align and fuse per output)."
    )
    print_shipped_models()
    return 0


def print_shipped_models() -> None:
    """The shipped models: name, member, the sensors they were trained on, and their source."""
    from spk2img.runtime.onnx_backend import graph_metadata, shipped_models

    shipped = shipped_models()
    if not shipped:
        print("\nno trained models are shipped with this installation")
        return
    print(f"\n{'shipped model':<14} {'member':<7} {'trained on sensors':<40} source")
    for name, path in shipped.items():
        meta = graph_metadata(path)
        sensors = meta.get("sensors", "unknown")
        print(f"{name:<14} {meta.get('member', '?'):<7} {sensors:<40} {meta.get('source', '?')}")
    print(
        "reconstruct and serve take --model NAME; each has a card: docs/model_card.md (default), "
        "docs/model_card_NAME.md"
    )
