"""Size and cost of a network: parameters and multiply-accumulates (MACs) per frame.

MACs count the products of convolution weights with their inputs — every convolution the
forward pass runs, the deformable convs' weights included (their grid_sample implementation
ends in a 1x1 convolution over the sampled taps, with exactly those MACs) — as the toolkits'
"GFLOPs" columns do; bilinear sampling, interpolation, activations and additions are left out.
GFLOPs = 2 x GMACs.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from .block_split import AlignFuseHead, BlockEncoder, model_code_names, repeated_code
from .config import Spk2ImgNetConfig
from .network import Spk2ImgNet


def count_parameters(model: nn.Module) -> int:
    """Trainable parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def count_macs(config: Spk2ImgNetConfig, height: int = 250, width: int = 400) -> int:
    """MACs to reconstruct one ``height x width`` frame (after padding to the pyramid's multiple).

    Runs the network on PyTorch's ``meta`` device (shapes only, no arithmetic) under a FLOP
    counter, so the count follows the code rather than a hand-kept formula.
    """
    with torch.device("meta"):
        model = Spk2ImgNet(config).eval()
        spikes = torch.zeros(1, config.window_frames, height, width)
    return _macs(lambda: model(spikes))


def count_stream_macs(
    config: Spk2ImgNetConfig, height: int = 250, width: int = 400
) -> tuple[int, int]:
    """``(encoder, head)``: MACs to encode one 13-frame block and to align and fuse one output
    from five block codes, at ``height x width`` — the cost per output of a stream that encodes
    each block once, when one new block arrives per output (centres 7 frames apart)."""
    with torch.device("meta"):
        model = Spk2ImgNet(config).eval()
        block = torch.zeros(1, config.block_frames, height, width)
    codes: list[torch.Tensor] = []
    encoder = _macs(lambda: codes.extend(BlockEncoder(model)(block)))
    inputs = repeated_code(tuple(codes), model_code_names(model), config.num_blocks)
    head = _macs(lambda: AlignFuseHead(model)(*inputs))
    return encoder, head


def _macs(run: Callable[[], object]) -> int:
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        run()
    return counter.get_total_flops() // 2
