"""The reconstruction methods behind one interface: a name -> a streaming reconstructor.

``net`` runs a model (any :data:`~spk2img.core.stream.Predictor`: onnxruntime or torch) on
41-frame windows; ``tfp`` and ``tfi`` are the classical methods of docs/format.md.
"""

from __future__ import annotations

from .adaptive import BalancedStream, check_quality
from .block_model import BlockCodec
from .block_stream import BlockReuseStream, reuses_blocks
from .errors import InputError
from .stream import NetStream, Predictor, StreamingReconstructor, TFIStream, TFPStream
from .windows import CenterPlan, net_window

METHODS = ("net", "tfp", "tfi")
DEFAULT_TFP_WINDOW = 41


def method_plan(
    method: str,
    centers: str | None,
    stride: int | None,
    window: int = DEFAULT_TFP_WINDOW,
    binning: int = 1,
) -> CenterPlan:
    """The centre plan for ``method``: the network uses 41 frames (41 x ``binning`` stream
    frames, :func:`~spk2img.core.windows.net_window`); TFP uses ``window``; TFI searches the
    whole stream but, like TFP, accepts only centres with a full ``window``."""
    return CenterPlan.parse(method_window(method, window, binning), centers, stride)


def method_window(
    method: str, window: int = DEFAULT_TFP_WINDOW, binning: int = 1, quality: str = "best"
) -> int:
    """Stream frames one reconstruction of ``method`` needs; checks the method, the quality
    and that ``binning`` applies (``net`` with quality ``best``)."""
    check_method(method)
    if binning != 1 and method != "net":
        raise InputError(f"binning is for method net, not {method}")
    if check_quality(quality) != "best" and binning != 1:
        raise InputError(f"binning is for quality best, not {quality}")
    return net_window(binning) if method == "net" else window


def check_method(method: str) -> str:
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}: choose one of {', '.join(METHODS)}")
    return method


def build_reconstructor(
    method: str,
    height: int,
    width: int,
    plan: CenterPlan,
    predict: Predictor | None = None,
    max_batch: int = 1,
    codec: BlockCodec | None = None,
    quality: str = "best",
    binning: int = 1,
) -> StreamingReconstructor:
    """A fresh streaming reconstructor for one stream of ``height x width`` frames.

    For ``net``, when ``codec`` is given and the plan's centres share blocks
    (:func:`~spk2img.core.block_stream.reuses_blocks`), each block is encoded once
    (:class:`~spk2img.core.block_stream.BlockReuseStream`); otherwise ``predict`` runs on every
    window, ``max_batch`` windows a call. ``quality`` (``net`` only, :mod:`spk2img.core.adaptive`):
    ``best`` as just said, ``balanced`` the network only on the tiles that move or are dim,
    ``fast`` TFP over the network's 41 frames. ``binning`` > 1 (``net``, quality ``best``
    only; ``plan`` from :func:`method_plan` with it) merges that many stream frames into each
    network frame (:class:`~spk2img.core.stream.NetStream`), every window whole.
    """
    method_window(method, plan.window, binning, quality)  # checks method, quality, binning
    if method == "tfp":
        return TFPStream(height, width, plan)
    if method == "tfi":
        return TFIStream(height, width, plan)
    if quality == "fast":
        return TFPStream(height, width, plan)
    if quality == "balanced" and predict is not None:
        return BalancedStream(height, width, plan, predict)
    if codec is not None and binning == 1 and reuses_blocks(plan, codec):
        return BlockReuseStream(height, width, plan, codec)
    if predict is None:
        raise InputError("method 'net' needs a model")
    return NetStream(height, width, plan, predict, max_batch, binning)
