"""The public in-process API: read and write spike streams, reconstruct frames.

Everything here is re-exported by :mod:`spk2img` (``spk2img.reconstruct``, …) and is what the
``spk2img reconstruct`` command itself calls. Conventions (docs/format.md):

- A spike stream is ``(T, H, W)``: ``T`` frames in time order, ``H`` rows (top row first),
  ``W`` columns, values 0 or 1 (any other value is an error).
- Reconstructed frames are ``(N, H, W) float32`` *linear* intensity in [0, 1] (a pixel of
  intensity ``I`` fires ``0.6 * I`` spikes a frame on average); PNGs apply display gamma.
- A centre is a frame index ``k`` of the stream; the frame reconstructed at ``k`` uses the
  window of frames ``k - window//2 .. k + window//2``: the model's window (its geometry's
  ``window_frames``, 41 frames for the shipped models), or that times ``binning`` on a dim
  stream.

Importing this module imports numpy only; onnxruntime or torch load when a
:class:`Reconstructor` for ``method="net"`` is built.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple, TypeAlias

import numpy as np

from spk2img.errors import InputError
from spk2img.io import spikes as _spikes
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, DatStream
from spk2img.model.config import PUBLISHED_GEOMETRY, Geometry
from spk2img.runtime.adaptive import QUALITIES
from spk2img.runtime.binning import suggest_binning
from spk2img.runtime.loader import LoadedNetwork, load_network
from spk2img.runtime.methods import (
    DEFAULT_TFP_WINDOW,
    METHODS,
    build_reconstructor,
    method_window,
)
from spk2img.runtime.stream import StreamingReconstructor, collect, frame_chunks
from spk2img.runtime.windows import CenterPlan, parse_centers

__all__ = [
    "METHODS",
    "QUALITIES",
    "Reconstruction",
    "Reconstructor",
    "Spikes",
    "reconstruct",
    "read_spikes",
    "suggest_binning",
    "write_spikes",
]

Spikes: TypeAlias = np.ndarray | DatStream
"""A spike stream: a ``(T, H, W)`` array of 0/1, or a memory-mapped ``.dat``
(:func:`read_spikes`), which supports ``len()``, ``.shape`` and frame slices ``s[a:b]``."""

Centers: TypeAlias = Sequence[int] | np.ndarray | str | None


class Reconstruction(NamedTuple):
    """What :func:`reconstruct` returns; unpacks as ``frames, centers = …``."""

    frames: np.ndarray
    """``(N, H, W) float32``: linear intensity in [0, 1], one image per centre."""
    centers: np.ndarray
    """``(N,) int64``: the stream frame index each image is centred on, ascending."""


def read_spikes(
    path: str | Path, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH
) -> Spikes:
    """Open a spike stream file.

    Args:
        path: a ``.dat`` (PKU format: no header, ``ceil(H*W/8)`` bytes a frame; opened
            memory-mapped, so a multi-GB recording is not loaded), a ``.npy`` (memory-mapped) or
            a ``.npz`` (the array ``spk`` or ``spikes``, else its only array) holding a
            ``(T, H, W)`` array of 0/1.
        height, width: the frame size in pixels, used by ``.dat`` only (default 250x400,
            the PKU camera's).

    Returns:
        ``(T, H, W)`` spikes, upright: an ``np.ndarray`` or, for ``.dat``, a
        :class:`~spk2img.io.spikes.DatStream` that decodes frames when sliced.

    Raises:
        FileNotFoundError: no such file.
        spk2img.io.spikes.SpikeFormatError: (a ``ValueError``) a file that is not a whole
            number of frames, an unknown suffix, an array that is not ``(T, H, W)`` or holds a
            value other than 0 and 1.
    """
    return _spikes.read_spikes(path, height, width)


def write_spikes(path: str | Path, spikes: np.ndarray) -> None:
    """Write ``(T, H, W)`` 0/1 spikes to ``path``: ``.dat`` (PKU format), ``.npy`` or ``.npz``
    (key ``spk``). Raises :class:`~spk2img.io.spikes.SpikeFormatError` for values other than
    0/1, a shape that is not ``(T, H, W)`` or an unknown suffix."""
    _spikes.write_spikes(path, spikes)


class Reconstructor:
    """A reconstruction method, with its model loaded once, for any number of streams.

    >>> recon = spk2img.Reconstructor("net")           # loads the shipped ONNX model
    >>> frames, centers = recon.reconstruct(spikes, stride=7)
    >>> frames.shape                                    # (N, H, W) float32, linear [0, 1]

    Args:
        method: ``"net"`` (the Spk2ImgNet model on its windows), ``"tfp"`` (the mean
            spike rate over ``window`` frames) or ``"tfi"`` (the inverse interval between the
            spikes around each centre).
        quality: for ``"net"``: ``"best"`` (the network on every pixel), ``"balanced"`` (the
            network only on 16x16 tiles that move or are dim, TFP elsewhere) or ``"fast"``
            (TFP over the network's window, no model loaded).
        window: TFP's window in frames (odd; default 41); TFI and TFP accept only centres
            with a full window. The network always uses its own window (:attr:`geometry`).
        model: an exported ONNX model file or a shipped model's name (``"default"``, …;
            :func:`spk2img.runtime.onnx_backend.shipped_models`). With ``block_reuse``, the
            block encoder and head graphs beside it (``MODEL.encoder.onnx``,
            ``MODEL.head.onnx``) are used when they exist.
        backend: ``"onnx"`` (onnxruntime; the serve extra) or ``"torch"`` (the train extra).
        checkpoint: the PyTorch checkpoint for ``backend="torch"`` (default: the ``.pt``
            shipped beside ``model``, or the shipped default's).
        threads: inference threads (None: the runtime's default).
        device: where onnxruntime runs the network: ``"cpu"``, ``"cuda"``, ``"tensorrt"`` or
            ``"auto"`` (CUDA when it can run here, else the CPU; docs/gpu.md). A GPU device
            onnxruntime cannot run raises :class:`~spk2img.runtime.onnx_backend.DeviceError`.
        batch: windows per network call when each window runs whole (the one-shot graph's
            batch axis is dynamic; more than 1 pays on a GPU).
        block_reuse: encode each block once when the centres share blocks (a stride that is a
            multiple of the block stride, 7 for the shipped models); the frames equal those of
            whole windows to float rounding.
        binning: for ``"net"`` with quality ``"best"``, on dim streams: merge this many
            consecutive frames into each of the network's frames (a spike where any fired), so a
            window spans ``F * binning`` frames (plus one when even) and a dim pixel fires as
            often per network frame as a bright one; trades time resolution for noise. 1 (the
            default) merges none; :func:`suggest_binning` picks one from a stream's firing rate.
        self_ensemble: for ``"net"``: also run the network on the stream's three mirror images
            (left-right, up-down, both) and average the four images mirrored back
            (:mod:`spk2img.runtime.self_ensemble`): four times the time for a better image.

    On the CPU the network keeps onnxruntime's memory arena: a stream's runs are of one frame
    size, so the arena saves allocating their buffers anew (8–21 % of a frame's time) and holds
    what one run needs anyway; a reconstructor used on ever larger frames keeps the largest's
    memory until it is deleted.
    """

    def __init__(
        self,
        method: str = "net",
        *,
        quality: str = "best",
        window: int = DEFAULT_TFP_WINDOW,
        model: str | Path | None = None,
        backend: str = "onnx",
        checkpoint: str | Path | None = None,
        threads: int | None = None,
        block_reuse: bool = True,
        device: str = "cpu",
        batch: int = 1,
        binning: int = 1,
        self_ensemble: bool = False,
    ):
        method_window(method, window, binning, quality)  # the one check, before a model loads
        self.method, self.quality, self.binning = method, quality, binning
        runs_network = method == "net" and quality != "fast"
        if device != "cpu" and not runs_network:
            raise InputError(f"device {device!r} is for method net with quality best or balanced")
        if self_ensemble and not runs_network:
            raise InputError("self_ensemble is for method net with quality best or balanced")
        self.network: LoadedNetwork | None = None
        """The loaded network (``method="net"`` unless quality ``"fast"``)."""
        if runs_network:
            self.network = load_network(
                model,
                backend=backend,
                checkpoint=checkpoint,
                device=device,
                threads=threads,
                block_reuse=block_reuse,
                batch=batch,
                memory_arena=True,
                self_ensemble=self_ensemble,
            )
        self.window = method_window(method, window, binning, quality, self.geometry)
        """Stream frames one reconstruction needs."""
        self.last_stream: StreamingReconstructor | None = None
        """The streaming reconstructor of the last call (its counters: ``blocks_encoded`` …)."""

    @property
    def geometry(self) -> Geometry:
        """The network's window and blocks (the published ones when no network is loaded)."""
        return self.network.geometry if self.network else PUBLISHED_GEOMETRY

    @property
    def device_note(self) -> str:
        """Why ``device="auto"`` chose the device it did ('' otherwise)."""
        return getattr(self.network.predict, "device_note", "") if self.network else ""

    def centers_for(self, n_frames: int, centers: Centers = None, stride: int | None = None):
        """The ``(N,) int64`` centres a call with these arguments yields on a stream of
        ``n_frames`` frames; raises :class:`~spk2img.runtime.windows.WindowError` (a
        ``ValueError``) when a centre has no full window."""
        return self._plan(centers, stride).centers_for(n_frames)

    def frames(
        self,
        spikes: Spikes,
        *,
        centers: Centers = None,
        stride: int | None = None,
        progress: Callable[[int], None] | None = None,
    ) -> Iterator[tuple[int, np.ndarray]]:
        """Reconstruct lazily: ``(centre, (H, W) float32 image)`` pairs in ascending centre
        order, each as soon as its window has been read. ``progress(n)`` is called after each
        input frame with the number of frames read so far. The arguments are checked before
        this returns; see :meth:`reconstruct`."""
        return self._frames(_checked_spikes(spikes), centers, stride, progress)

    def _frames(self, spikes: Spikes, centers: Centers, stride: int | None, progress):
        n_frames, height, width = spikes.shape
        plan = self._plan(centers, stride)
        plan.centers_for(n_frames)  # a centre without a full window: fail before any work
        if self.network is not None:
            stream = self.network.reconstructor(height, width, plan, self.quality, self.binning)
        else:
            stream = build_reconstructor(self.method, height, width, plan, quality=self.quality)
        self.last_stream = stream
        return _run(stream, spikes, progress)

    def reconstruct(
        self, spikes: Spikes, *, centers: Centers = None, stride: int | None = None
    ) -> Reconstruction:
        """Reconstruct frames of one spike stream.

        Args:
            spikes: ``(T, H, W)`` 0/1 spikes (an array or what :func:`read_spikes` returns).
            centers: the frame indices to reconstruct (a sequence of ints or ``"40,80"``);
                each needs a full window: ``window//2 <= k < T - window//2``.
            stride: instead, every ``stride``-th centre from the first with a full window.
                Neither: every ``block_stride``-th (the model's, 7 for the shipped models), so
                that each block is encoded once.

        Returns:
            :class:`Reconstruction`: ``frames (N, H, W) float32`` linear intensity in [0, 1]
            and ``centers (N,) int64``.

        Raises:
            ValueError: (:class:`~spk2img.errors.InputError`) spikes that are not a
                ``(T, H, W)`` 0/1 array, a centre without a full window, both ``centers`` and
                ``stride``.
        """
        spikes = _checked_spikes(spikes)
        pairs = self._frames(spikes, centers, stride, None)
        return Reconstruction(*collect(pairs, *spikes.shape[1:]))

    def _plan(self, centers: Centers, stride: int | None) -> CenterPlan:
        if isinstance(centers, str):
            centers = parse_centers(centers)
        if centers is None and stride is None:
            stride = self.geometry.block_stride
        return CenterPlan(self.window, centers, stride)


def reconstruct(
    spikes: Spikes,
    *,
    centers: Centers = None,
    stride: int | None = None,
    method: str = "net",
    quality: str = "best",
    window: int = DEFAULT_TFP_WINDOW,
    model: str | Path | None = None,
    backend: str = "onnx",
    threads: int | None = None,
    binning: int = 1,
) -> Reconstruction:
    """Reconstruct frames of one spike stream in one call.

    >>> frames, centers = spk2img.reconstruct(spk2img.read_spikes("rec.dat"), stride=20)

    ``spikes`` is ``(T, H, W)`` 0/1; the result is ``frames (N, H, W) float32`` linear
    intensity in [0, 1] and ``centers (N,) int64`` frame indices. The arguments are those of
    :class:`Reconstructor` and :meth:`Reconstructor.reconstruct`; build a
    :class:`Reconstructor` once to reconstruct many streams with one loaded model.
    """
    recon = Reconstructor(
        method,
        quality=quality,
        window=window,
        model=model,
        backend=backend,
        threads=threads,
        binning=binning,
    )
    return recon.reconstruct(spikes, centers=centers, stride=stride)


def _checked_spikes(spikes: Spikes) -> Spikes:
    """A :class:`DatStream` as is (its frames are 0/1 by construction); an array checked as
    ``(T, H, W)`` 0/1, up front when in memory, per chunk as it is read when memory-mapped
    (:func:`read_spikes` checked it when it opened it)."""
    if isinstance(spikes, DatStream):
        return spikes
    array = spikes if isinstance(spikes, np.ndarray) else np.asarray(spikes)
    if isinstance(array, np.memmap):
        if array.ndim != 3 or array.size == 0:
            raise _spikes.SpikeFormatError(f"expected a (T, H, W) array, got {array.shape}")
        return array
    return _spikes.check_spike_values(array)


def _run(
    stream: StreamingReconstructor, spikes: Spikes, progress: Callable[[int], None] | None
) -> Iterator[tuple[int, np.ndarray]]:
    """Push the stream a frame at a time, so each centre comes out as soon as it is done."""
    read = 0
    for chunk in frame_chunks(spikes):
        for i in range(len(chunk)):
            yield from stream.push(chunk[i : i + 1])
            read += 1
            if progress is not None:
                progress(read)
    yield from stream.close()
