"""``spk2img models``: the Spk2ImgNet family members, their parameters and cost per frame."""

from __future__ import annotations

import argparse

from spk2img.core.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, check_size


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "models",
        help="list the network family: parameters and G MACs per frame",
        description="List the Spk2ImgNet family members with their parameter counts and "
        "multiply-accumulates (MACs) per frame of the given size. GFLOPs = 2 x G MACs.",
    )
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width")


def run(args: argparse.Namespace) -> int:
    check_size(args.height, args.width)
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
    return 0
