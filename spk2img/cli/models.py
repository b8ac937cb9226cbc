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

    from spk2img.training.complexity import count_macs, count_parameters
    from spk2img.training.config import MEMBERS
    from spk2img.training.network import build_model

    size = f"G MACs/{args.height}x{args.width}"
    print(f"{'member':<8} {'parameters':>12} {size:>18}")
    for name, config in MEMBERS.items():
        with torch.device("meta"):
            params = count_parameters(build_model(config))
        macs = count_macs(config, args.height, args.width)
        print(f"{name:<8} {params:>12,} {macs / 1e9:>18.1f}")
    print("MACs count weight multiply-accumulates of the convolutions; GFLOPs = 2 x G MACs.")
    return 0
