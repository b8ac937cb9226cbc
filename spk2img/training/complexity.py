"""Size and cost of a network: parameters and multiply-accumulates (MACs) per frame.

MACs count the products of convolution weights with their inputs (``nn.Conv2d`` and the
weights of :class:`ModulatedDeformConv2d`), as the toolkits' "GFLOPs" columns do; bilinear
sampling, interpolation, activations and additions are left out. GFLOPs = 2 x GMACs.
"""

from __future__ import annotations

import torch
from torch import nn

from .config import Spk2ImgNetConfig
from .deform_conv import ModulatedDeformConv2d
from .network import Spk2ImgNet


def count_parameters(model: nn.Module) -> int:
    """Trainable parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def count_macs(config: Spk2ImgNetConfig, height: int = 250, width: int = 400) -> int:
    """MACs to reconstruct one ``height x width`` frame (after padding to the pyramid's multiple).

    Runs the network on PyTorch's ``meta`` device (shapes only, no arithmetic) with forward hooks
    on every convolution, so the count follows the code rather than a hand-kept formula.
    """
    macs = 0

    def conv_hook(module: nn.Conv2d, _inputs: tuple, output: torch.Tensor) -> None:
        nonlocal macs
        macs += output.numel() * module.weight[0].numel()  # (c_in / groups) * kh * kw per output

    def deform_hook(module: ModulatedDeformConv2d, _inputs: tuple, output: torch.Tensor) -> None:
        nonlocal macs
        macs += output.numel() * module.weight[0].numel()

    with torch.device("meta"):
        model = Spk2ImgNet(config).eval()
        spikes = torch.zeros(1, config.window_frames, height, width)
    for module in model.modules():
        if isinstance(module, nn.Conv2d):
            module.register_forward_hook(conv_hook)
        elif isinstance(module, ModulatedDeformConv2d):
            module.register_forward_hook(deform_hook)
    with torch.no_grad():
        model(spikes)
    return macs
