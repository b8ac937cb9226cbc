"""Running an exported Spk2ImgNet ONNX graph with onnxruntime (no torch needed)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from .errors import InputError

DEFAULT_MODEL = "spk2img-default.onnx"


def default_model_path() -> Path:
    """The shipped default model's ONNX file (inside the installed package)."""
    return Path(str(resources.files("spk2img") / "assets" / "models" / DEFAULT_MODEL))


class OnnxModel:
    """An ONNX reconstruction graph: ``(B, 41, H, W)`` 0/1 float32 -> ``(B, H, W)`` float32.

    ``threads`` sets onnxruntime's intra-op threads (None: onnxruntime's default).
    ``metadata`` holds the graph's ``metadata_props`` (name, version, config, sha256 …).
    """

    def __init__(self, path: str | Path | None = None, threads: int | None = None):
        self.path = Path(path) if path is not None else default_model_path()
        self.session = cpu_session(self.path, threads)
        self.input_name = self.session.get_inputs()[0].name
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)

    def __call__(self, windows: np.ndarray) -> np.ndarray:
        """Reconstruct ``(B, 41, H, W)`` windows into ``(B, H, W)`` linear intensity in [0, 1]."""
        (out,) = self.session.run(
            None, {self.input_name: np.ascontiguousarray(windows, np.float32)}
        )
        return out[:, 0]


def cpu_session(path: Path, threads: int | None = None):
    """An onnxruntime CPU session for ``path`` with ``threads`` intra-op threads (None:
    onnxruntime's default); :class:`InputError` for a missing or unloadable file."""
    import onnxruntime as ort

    if not path.is_file():
        raise InputError(f"no such model file: {path}")
    options = ort.SessionOptions()
    options.enable_cpu_mem_arena = False  # else one large request pins its memory for good
    if threads:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own untyped errors for bad files
        raise InputError(f"{path}: not a loadable ONNX model ({exc})") from exc
