"""The reconstruction methods behind one interface: a name -> a streaming reconstructor.

``net`` runs a model (any :data:`~spk2img.runtime.stream.Predictor`: onnxruntime or torch) on
the windows its :class:`~spk2img.model.config.Geometry` asks for; ``tfp`` and ``tfi`` are the
classical methods of docs/format.md.
"""

from __future__ import annotations

from spk2img.errors import InputError
from spk2img.model.config import PUBLISHED_GEOMETRY, Geometry
from spk2img.runtime.adaptive import BalancedStream, check_quality
from spk2img.runtime.block_codec import BlockCodec
from spk2img.runtime.block_stream import BlockReuseStream, reuses_blocks
from spk2img.runtime.stream import (
    NetStream,
    Predictor,
    StreamingReconstructor,
    TFIStream,
    TFPStream,
)
from spk2img.runtime.windows import CenterPlan, net_window

METHODS = ("net", "tfp", "tfi")
DEFAULT_TFP_WINDOW = PUBLISHED_GEOMETRY.window_frames
"""TFP's and TFI's window when none is given: the published network's (41 frames)."""


def method_plan(
    method: str,
    centers: str | None,
    stride: int | None,
    window: int = DEFAULT_TFP_WINDOW,
    binning: int = 1,
    geometry: Geometry = PUBLISHED_GEOMETRY,
    quality: str = "best",
) -> CenterPlan:
    """The centre plan for ``method``: the network uses its ``geometry``'s frames (times
    ``binning`` stream frames, :func:`~spk2img.runtime.windows.net_window`); TFP uses ``window``;
    TFI searches the whole stream but, like TFP, accepts only centres with a full ``window``.
    The arguments are checked by :func:`method_window`."""
    window = method_window(method, window, binning, quality, geometry)
    return CenterPlan.parse(window, centers, stride)


def method_window(
    method: str,
    window: int = DEFAULT_TFP_WINDOW,
    binning: int = 1,
    quality: str = "best",
    geometry: Geometry = PUBLISHED_GEOMETRY,
) -> int:
    """Stream frames one reconstruction of ``method`` needs (for ``net``, the window of the
    model's ``geometry``, the published one by default).

    The one check of a request's method, quality and binning, for the API, the CLI and the
    service: :class:`InputError` for an unknown method or quality, a quality other than
    ``best`` for a classical method, and a ``binning`` other than 1 outside ``net`` with
    quality ``best``."""
    check_method(method)
    if check_quality(quality) != "best" and method != "net":
        raise InputError(f"quality is for method net, not {method}")
    if binning != 1 and method != "net":
        raise InputError(f"binning is for method net, not {method}")
    if quality != "best" and binning != 1:
        raise InputError(f"binning is for quality best, not {quality}")
    return net_window(geometry.window_frames, binning) if method == "net" else window


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
    geometry: Geometry | None = None,
) -> StreamingReconstructor:
    """A fresh streaming reconstructor for one stream of ``height x width`` frames.

    For ``net``, when ``codec`` is given and the plan's centres share blocks
    (:func:`~spk2img.runtime.block_stream.reuses_blocks`), each block is encoded once
    (:class:`~spk2img.runtime.block_stream.BlockReuseStream`); otherwise ``predict`` runs on every
    window, ``max_batch`` windows a call. ``quality`` (``net`` only,
    :mod:`spk2img.runtime.adaptive`): ``best`` as just said, ``balanced`` the network only on the
    tiles that move or are dim, ``fast`` TFP over the network's frames. ``binning`` > 1 (``net``,
    quality ``best``
    only; ``plan`` from :func:`method_plan` with it) merges that many stream frames into each
    network frame (:class:`~spk2img.runtime.stream.NetStream`), every window whole. ``geometry``
    is the network's (None: the one ``predict`` or ``codec`` carries, else the published one); a
    plan whose window is not the one ``method`` needs raises :class:`InputError`.
    """
    geometry = geometry or getattr(predict, "geometry", None) or getattr(codec, "geometry", None)
    window = method_window(
        method, plan.window, binning, quality, geometry or PUBLISHED_GEOMETRY
    )  # checks the method, the quality and the binning too
    if window != plan.window:
        raise InputError(
            f"method {method} with binning {binning} needs a {window}-frame window, got "
            f"{plan.window}"
        )
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
