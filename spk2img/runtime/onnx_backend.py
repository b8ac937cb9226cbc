"""Running an exported Spk2ImgNet ONNX graph with onnxruntime (no torch needed).

:func:`create_session` is the one place that turns a *device* into onnxruntime execution
providers and session options; the one-shot model (:class:`OnnxModel`), the block encoder and
head (:class:`~spk2img.runtime.block_codec.OnnxBlockCodec`), the service and the benchmark all
create their sessions through it.

Devices (docs/gpu.md):

- ``cpu``: onnxruntime's CPU provider (the ``onnxruntime`` package, the serve extra).
- ``cuda``: the CUDA provider (the ``onnxruntime-gpu`` package, the gpu extra), CPU for the
  operators CUDA lacks.
- ``tensorrt``: the TensorRT provider, then CUDA, then CPU (onnxruntime-gpu with TensorRT's
  libraries installed); engines are cached under :data:`TRT_CACHE`.
- ``auto``: ``cuda`` when onnxruntime can run it here, else ``cpu``; the choice and why are
  in :attr:`Session.note`.

Asking for ``cuda`` or ``tensorrt`` where onnxruntime cannot run that provider raises
:class:`DeviceError` (an :class:`InputError`: exit code 2 from the CLI) with one line; nothing
falls back to the CPU silently.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from spk2img.errors import InputError
from spk2img.model.config import Geometry

DEFAULT_MODEL = "spk2img-default.onnx"

DEVICES = ("cpu", "cuda", "tensorrt", "auto")
"""What ``--device`` accepts."""
PROVIDERS = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
}
"""The onnxruntime provider each concrete device runs on first."""
TRT_CACHE = Path(os.environ.get("SPK2IMG_TRT_CACHE", Path.home() / ".cache" / "spk2img" / "trt"))
"""Where TensorRT engines are cached between runs (``SPK2IMG_TRT_CACHE``)."""
GPU_INSTALL = 'pip uninstall -y onnxruntime && pip install -e ".[gpu]"'
"""How to swap the CPU build of onnxruntime for the GPU one (they exclude each other)."""


class DeviceError(InputError):
    """A device this onnxruntime cannot run here (no such provider, or it failed to start)."""


def default_model_path() -> Path:
    """The shipped default model's ONNX file (inside the installed package)."""
    return shipped_models_dir() / DEFAULT_MODEL


def shipped_models_dir() -> Path:
    """Where the package keeps its trained models (``spk2img-<name>.onnx`` and its parts)."""
    return Path(str(resources.files("spk2img") / "assets" / "models"))


def shipped_models() -> dict[str, Path]:
    """``{name: one-shot ONNX file}`` of the trained models this installation ships
    (``spk2img-default.onnx`` is ``default``; block-graph parts are not models of their own)."""
    folder = shipped_models_dir()
    files = sorted(folder.glob("spk2img-*.onnx")) if folder.is_dir() else []
    return {
        path.name.removeprefix("spk2img-").removesuffix(".onnx"): path
        for path in files
        if path.suffixes == [".onnx"]
    }


def graph_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file (spk2img.export.metadata), read by onnxruntime
    (a one-thread CPU session from :func:`create_session`)."""
    session = create_session(path, threads=1).session
    return dict(session.get_modelmeta().custom_metadata_map)


def graph_geometry(metadata: dict[str, str], input_shape: list) -> Geometry:
    """The geometry of a graph: the one its ``config`` metadata records (spk2img's exports), else,
    for a graph exported elsewhere, one block of the frames its input ``(B, F, H, W)`` fixes;
    :class:`InputError` when neither says how many frames it reads."""
    if "config" in metadata:
        return Geometry.from_metadata(metadata)
    frames = input_shape[1] if len(input_shape) == 4 else None
    if not isinstance(frames, int) or frames < 1 or frames % 2 == 0:
        raise InputError(
            "the graph records no spk2img config and its input (B, F, H, W) does not fix an odd "
            f"number of frames F (input shape {input_shape}): export it with spk2img export"
        )
    return Geometry(block_frames=frames, block_stride=1, num_blocks=1)


def model_path(model: str | Path | None) -> Path:
    """The ONNX file ``model`` names: None is the shipped default, an existing file is itself,
    else a shipped model's name (:func:`shipped_models`) is its file; :class:`InputError` when
    it is neither."""
    if model is None:
        return default_model_path()
    path = Path(model)
    if path.is_file():
        return path
    shipped = shipped_models()
    if str(model) in shipped:
        return shipped[str(model)]
    names = ", ".join(shipped) or "none installed"
    raise InputError(
        f"no model file {str(model)!r}: give an ONNX file or a shipped model's name ({names})"
    )


def check_device(device: str) -> str:
    """``device`` if it is one of :data:`DEVICES`, else :class:`InputError`."""
    if device not in DEVICES:
        raise InputError(f"unknown device {device!r}: choose one of {', '.join(DEVICES)}")
    return device


def available_providers() -> list[str]:
    """The execution providers this onnxruntime build has (not a promise that a GPU is there)."""
    import onnxruntime as ort

    return list(ort.get_available_providers())


def resolve_device(device: str, providers: list[str] | None = None) -> tuple[str, str]:
    """The concrete device (``cpu``, ``cuda`` or ``tensorrt``) to try for ``device``, and a
    note on the choice ('' unless ``auto``); :class:`DeviceError` for ``cuda``/``tensorrt``
    when onnxruntime has no such provider. ``providers``: default :func:`available_providers`."""
    check_device(device)
    providers = available_providers() if providers is None else providers
    if device == "auto":
        if PROVIDERS["cuda"] in providers:
            return "cuda", "--device auto chose cuda (onnxruntime has CUDAExecutionProvider)"
        return "cpu", (
            "--device auto chose cpu (this onnxruntime has no CUDAExecutionProvider; "
            f"providers: {', '.join(providers)})"
        )
    if PROVIDERS[device] not in providers:
        raise DeviceError(missing_provider(device, providers))
    return device, ""


def missing_provider(device: str, providers: list[str]) -> str:
    """The one line for a device whose provider this onnxruntime lacks."""
    import onnxruntime as ort

    fix = GPU_INSTALL
    if device == "tensorrt" and PROVIDERS["cuda"] in providers:
        fix = "install TensorRT's libraries (docs/gpu.md)"
    return (
        f"device {device!r} needs onnxruntime's {PROVIDERS[device]}, which onnxruntime "
        f"{ort.__version__} here does not have (it has {', '.join(providers)}): {fix}, "
        "or use --device cpu or --device auto"
    )


def provider_chain(device: str, fp16: bool = False) -> list[tuple[str, dict]]:
    """The ``(provider, options)`` list of a concrete device, first choice first (onnxruntime
    places each operator on the first provider that has a kernel for it).

    CUDA: the memory arena grows by what is asked for, not in doubling chunks (one large
    request must not pin a doubled arena for good, as on the CPU). TensorRT: engines cached in
    :data:`TRT_CACHE`, fp16 kernels allowed when ``fp16``.
    """
    cuda = ("CUDAExecutionProvider", {"arena_extend_strategy": "kSameAsRequested"})
    cpu = ("CPUExecutionProvider", {})
    if device == "cpu":
        return [cpu]
    if device == "cuda":
        return [cuda, cpu]
    if device == "tensorrt":
        trt = {
            "trt_engine_cache_enable": "True",
            "trt_engine_cache_path": str(TRT_CACHE),
            "trt_fp16_enable": "True" if fp16 else "False",
        }
        return [("TensorrtExecutionProvider", trt), cuda, cpu]
    raise ValueError(f"not a concrete device: {device!r}")


def session_options(threads: int | None = None, memory_arena: bool = False):
    """onnxruntime session options: ``threads`` intra-op threads (None: onnxruntime's default,
    also for the CPU-side operators of a GPU session), the CPU memory arena on or off.

    Without the arena, memory goes back to the system after each run; with it, a session keeps
    its largest run's memory (measured: ``default`` holds 1.3 GB after a 250x400 run, 4.1 GB
    after a 500x800 one, 0.3 GB without the arena), so one large request pins its memory for
    good: a service runs without it. The arena saves allocating each run's buffers anew: 12 %
    of ``default``'s time a 250x400 frame on 2 threads, 21 % of ``tiny``'s, 8 % of ``cpu``'s
    (measured side by side); a stream of one frame size, whose every run needs that memory
    anyway, runs with it.
    """
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.enable_cpu_mem_arena = memory_arena
    if threads:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    return options


@dataclass
class Session:
    """An onnxruntime session and where it runs."""

    session: object
    """The ``onnxruntime.InferenceSession``."""
    device: str
    """The concrete device it runs on: ``cpu``, ``cuda`` or ``tensorrt``."""
    note: str = ""
    """Why ``auto`` chose :attr:`device` ('' when a device was named)."""

    @property
    def provider(self) -> str:
        """The execution provider actually in use (the first the session holds)."""
        return self.session.get_providers()[0]


def create_session(
    path: str | Path,
    threads: int | None = None,
    device: str = "cpu",
    fp16: bool = False,
    memory_arena: bool = False,
) -> Session:
    """An onnxruntime session for ``path`` on ``device`` (:data:`DEVICES`), with the CPU memory
    arena when ``memory_arena`` (:func:`session_options`).

    Raises :class:`InputError` for a missing or unloadable file and :class:`DeviceError` when
    ``cuda``/``tensorrt`` cannot run here: no such provider, or onnxruntime has it but fell
    back to the CPU when it started (no GPU, or CUDA/cuDNN libraries missing). ``auto`` then
    runs on the CPU and says so in :attr:`Session.note`.
    """
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such model file: {path}")
    concrete, note = resolve_device(device)
    if concrete == "tensorrt":
        TRT_CACHE.mkdir(parents=True, exist_ok=True)
    chain = provider_chain(concrete, fp16)
    try:
        session = ort.InferenceSession(
            str(path),
            session_options(threads, memory_arena),
            providers=[name for name, _ in chain],
            provider_options=[options for _, options in chain],
        )
    except Exception as exc:  # onnxruntime raises its own untyped errors for bad files
        raise InputError(f"{path}: not a loadable ONNX model ({exc})") from exc
    in_use = session.get_providers()[0]
    if in_use != PROVIDERS[concrete]:  # onnxruntime-gpu falls back quietly when CUDA fails
        reason = (
            f"onnxruntime has {PROVIDERS[concrete]} but could not start it (no GPU, or its "
            "CUDA/cuDNN libraries are missing: see onnxruntime's warning above and docs/gpu.md)"
        )
        if device != "auto":
            raise DeviceError(f"device {device!r}: {reason}")
        fallback = create_session(path, threads, "cpu", memory_arena=memory_arena)
        fallback.note = f"--device auto chose cpu ({reason})"
        return fallback
    return Session(session, concrete, note)


def run_session(
    session: Session, feeds: dict[str, np.ndarray], outputs: list[str], io_binding: bool
) -> list[np.ndarray]:
    """Run ``session`` on ``feeds``; the ``outputs`` as numpy arrays.

    With ``io_binding`` the inputs are bound from host memory (copied to the device once, by
    onnxruntime) and the outputs allocated on the session's device and copied back once, so
    no intermediate host copy is made on either side; the same path runs on the CPU provider
    (the tests check it there).
    """
    if not io_binding:
        return session.session.run(outputs, feeds)
    binding = session.session.io_binding()
    for name, array in feeds.items():
        binding.bind_cpu_input(name, array)
    where = "cpu" if session.device == "cpu" else "cuda"
    for name in outputs:
        binding.bind_output(name, where)
    session.session.run_with_iobinding(binding)
    return binding.copy_outputs_to_cpu()


class OnnxModel:
    """An ONNX reconstruction graph: ``(B, F, H, W)`` 0/1 float32 -> ``(B, H, W)`` float32.

    ``threads`` sets onnxruntime's intra-op threads (None: onnxruntime's default); ``device``
    is one of :data:`DEVICES` (:func:`create_session`); ``io_binding`` (default: on a GPU)
    runs through onnxruntime's IO binding (:func:`run_session`); ``memory_arena`` keeps
    onnxruntime's CPU memory arena (:func:`session_options`). The graph's batch axis is
    dynamic: one call may reconstruct many centres. ``metadata`` holds the graph's
    ``metadata_props`` (name, version, config, sha256 …); ``geometry`` the frames ``F`` it
    reads and their blocks (:func:`graph_geometry`); ``device``, ``provider`` and
    ``device_note`` say where it runs.
    """

    def __init__(
        self,
        path: str | Path | None = None,
        threads: int | None = None,
        device: str = "cpu",
        io_binding: bool | None = None,
        memory_arena: bool = False,
    ):
        self.path = model_path(path)
        self.runner = create_session(self.path, threads, device, memory_arena=memory_arena)
        self.session = self.runner.session
        self.input_name = self.session.get_inputs()[0].name
        self.output_name = self.session.get_outputs()[0].name
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        self.geometry = graph_geometry(self.metadata, self.session.get_inputs()[0].shape)
        self.io_binding = self.device != "cpu" if io_binding is None else io_binding

    @property
    def device(self) -> str:
        """The concrete device the graph runs on (``cpu``, ``cuda`` or ``tensorrt``)."""
        return self.runner.device

    @property
    def provider(self) -> str:
        """The onnxruntime execution provider in use."""
        return self.runner.provider

    @property
    def device_note(self) -> str:
        """Why ``--device auto`` chose :attr:`device` ('' when a device was named)."""
        return self.runner.note

    def __call__(self, windows: np.ndarray) -> np.ndarray:
        """Reconstruct ``(B, F, H, W)`` windows into ``(B, H, W)`` linear intensity in [0, 1]."""
        feeds = {self.input_name: np.ascontiguousarray(windows, np.float32)}
        (out,) = run_session(self.runner, feeds, [self.output_name], self.io_binding)
        return out[:, 0]
