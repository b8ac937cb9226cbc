"""Loading a network for inference: the one place that turns a model name or file, a backend and
a device into something ready to reconstruct frames: the API, the service, the bench, the model
cards and ``spk2img verify`` load through :func:`load_network` (verify streams the block graphs
of a reduced-precision variant, which has no one-shot graph beside it, through
:class:`~spk2img.runtime.block_codec.OnnxBlockCodec` itself).

A :class:`LoadedNetwork` holds the network on whole windows (onnxruntime's
:class:`~spk2img.runtime.onnx_backend.OnnxModel` or torch's
:class:`~spk2img.runtime.torch_backend.TorchPredictor`), its block codec when the centres of a
stream may share blocks, and the geometry the model carries: the runtime takes every window,
block and stride from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img.errors import InputError
from spk2img.model.config import Geometry
from spk2img.runtime.block_codec import BlockCodec
from spk2img.runtime.methods import build_reconstructor
from spk2img.runtime.self_ensemble import SelfEnsembleCodec, SelfEnsemblePredictor
from spk2img.runtime.stream import Predictor, StreamingReconstructor
from spk2img.runtime.windows import CenterPlan

BACKENDS = ("onnx", "torch")
"""What runs the network: onnxruntime (the serve extra) or PyTorch (the train extra)."""
WARMUP_SIZE = 32
"""Side of the zero window a network runs once when it is warmed up (pixels)."""


@dataclass
class LoadedNetwork:
    """A network ready to run: ``predict`` on whole windows, ``codec`` (or None) on blocks."""

    predict: Predictor
    """``(B, F, H, W)`` 0/1 windows -> ``(B, H, W)`` linear intensity."""
    geometry: Geometry
    """The frames the network reads and their blocks, as the model records them."""
    codec: BlockCodec | None = None
    """The block encoder and align-and-fuse head (None: every window runs whole)."""
    batch: int = 1
    """Windows per call when windows run whole."""

    def warm_up(self, height: int = WARMUP_SIZE, width: int = WARMUP_SIZE) -> None:
        """Run the network (and the block encoder and head) once on zeros of ``height x width``,
        so that the first real call does not pay for the runtime's first-call set-up."""
        geometry = self.geometry
        self.predict(np.zeros((1, geometry.window_frames, height, width), np.float32))
        if self.codec is not None:
            code = self.codec.encode(np.zeros((geometry.block_frames, height, width), np.float32))
            self.codec.head([code] * geometry.num_blocks, height, width)

    def reconstructor(
        self,
        height: int,
        width: int,
        plan: CenterPlan,
        quality: str = "best",
        binning: int = 1,
    ) -> StreamingReconstructor:
        """A fresh streaming reconstructor of this network for one ``height x width`` stream
        (:func:`~spk2img.runtime.methods.build_reconstructor`)."""
        return build_reconstructor(
            "net",
            height,
            width,
            plan,
            self.predict,
            self.batch,
            codec=self.codec,
            quality=quality,
            binning=binning,
            geometry=self.geometry,
        )


def load_network(
    model: str | Path | None = None,
    *,
    backend: str = "onnx",
    checkpoint: str | Path | None = None,
    device: str = "cpu",
    threads: int | None = None,
    block_reuse: bool = True,
    batch: int = 1,
    warm_up: bool = True,
    memory_arena: bool = False,
    self_ensemble: bool = False,
) -> LoadedNetwork:
    """Load a network ready to reconstruct.

    Args:
        model: an exported ONNX file or a shipped model's name (None: the shipped default).
        backend: one of :data:`BACKENDS`.
        checkpoint: for ``torch``: the checkpoint to run (default: the ``.pt`` shipped beside
            ``model``, or the shipped default's).
        device: for ``onnx``: ``cpu``, ``cuda``, ``tensorrt`` or ``auto`` (docs/gpu.md).
        threads: inference threads (None: the runtime's default).
        block_reuse: also load the block encoder and head (the ONNX graphs beside the model,
            when there; the torch network itself), so streams encode each block once.
        batch: windows per call when windows run whole.
        warm_up: run :meth:`LoadedNetwork.warm_up` before returning.
        memory_arena: for ``onnx``: keep onnxruntime's CPU memory arena, faster for a stream of
            one frame size, holding its largest run's memory for good
            (:func:`~spk2img.runtime.onnx_backend.session_options`).
        self_ensemble: run the network on the windows and their three mirror images and
            average the four images mirrored back (:mod:`spk2img.runtime.self_ensemble`):
            four times the work, a sharper average; on a GPU the four views run as one batch.

    Raises:
        InputError: an unknown backend, a missing model, a device that cannot run here.
        ModuleNotFoundError: the backend's extra is not installed (the message names it).
    """
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r}: choose one of {', '.join(BACKENDS)}")
    if checkpoint is not None and backend != "torch":
        raise InputError(
            "a checkpoint is for backend torch: backend onnx runs the model's graph (add "
            "--backend torch, or drop --checkpoint)"
        )
    if backend == "torch" and device != "cpu":
        raise InputError(f"device {device!r} is for the onnx backend (torch runs on the CPU)")
    if batch < 1:
        raise InputError(f"batch must be >= 1, got {batch}")
    extra = "train" if backend == "torch" else "serve"
    try:
        if backend == "torch":
            network = _torch_network(model, checkpoint, threads, block_reuse, batch)
        else:
            network = _onnx_network(model, device, threads, block_reuse, batch, memory_arena)
        if self_ensemble:
            on_gpu = backend == "onnx" and network.predict.device != "cpu"
            network = _self_ensemble(network, batch_views=on_gpu)
    except ModuleNotFoundError as exc:  # the same words as the CLI's (spk2img.cli.extras)
        raise ModuleNotFoundError(
            f"method 'net' with backend {backend!r} needs the {extra} extra (not installed: "
            f'{exc.name}): pip install -e ".[{extra}]" in a checkout, or pip install '
            f'"spk2img[{extra}]"',
            name=exc.name,
        ) from exc
    if warm_up:
        network.warm_up()
    return network


def _self_ensemble(network: LoadedNetwork, batch_views: bool) -> LoadedNetwork:
    """``network`` on the four mirrored views (one call of all four when ``batch_views``)."""
    codec = SelfEnsembleCodec(network.codec) if network.codec else None
    predict = SelfEnsemblePredictor(network.predict, batch_views)
    return LoadedNetwork(predict, network.geometry, codec, network.batch)


def _onnx_network(
    model, device: str, threads, block_reuse: bool, batch: int, memory_arena: bool
) -> LoadedNetwork:
    from spk2img.runtime.block_codec import OnnxBlockCodec, block_graph_paths
    from spk2img.runtime.onnx_backend import OnnxModel

    predict = OnnxModel(model, threads=threads, device=device, memory_arena=memory_arena)
    codec = None
    if block_reuse and all(path.is_file() for path in block_graph_paths(predict.path).values()):
        codec = OnnxBlockCodec(
            predict.path, threads=threads, device=predict.device, memory_arena=memory_arena
        )
    return LoadedNetwork(predict, predict.geometry, codec, batch)


def _torch_network(model, checkpoint, threads, block_reuse: bool, batch: int) -> LoadedNetwork:
    from spk2img.runtime.torch_backend import TorchPredictor

    predict = TorchPredictor(_torch_checkpoint(model, checkpoint), threads=threads)
    return LoadedNetwork(predict, predict.geometry, predict if block_reuse else None, batch)


def _torch_checkpoint(model, checkpoint):
    """The checkpoint the torch backend runs: ``checkpoint``, else the ``.pt`` shipped beside
    ``model`` (a shipped model's name or an ONNX file), else the shipped default (None)."""
    if model is None:
        return checkpoint
    if checkpoint is not None:
        raise InputError("the torch backend runs one checkpoint: give a model or a checkpoint")
    from spk2img.runtime.onnx_backend import model_path

    beside = model_path(model).with_suffix(".pt")
    if not beside.is_file():
        raise InputError(f"no checkpoint {beside.name} beside model {str(model)!r} for torch")
    return beside
