"""The networks to benchmark: their weights, the ONNX graphs of each backend and their cost.

Family members get random weights (seeded, never trained: timed, not scored); the shipped model
and checkpoints named on the command line are trained. Every ONNX graph is made by
:mod:`spk2img.export` — the shipped ONNX file itself serves the ``onnx`` backend.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .rows import BACKENDS, NetRow

INIT_SEED = 0
"""``torch.manual_seed`` of the random weights of the family members."""


@dataclass(frozen=True)
class Weights:
    """One set of network weights to benchmark."""

    name: str
    """Row label: a member name (``tiny``) or a trained model's name (``shipped``)."""
    checkpoint: Path
    """The checkpoint (config and weights, :mod:`spk2img.training.checkpoint`)."""
    trained: bool
    """Whether the weights were trained (untrained ones are timed but never scored)."""
    onnx: Path | None = None
    """An existing grid_sample ONNX graph of these weights (the shipped one), else exported."""


def random_member(member: str, directory: Path) -> Weights:
    """Family member ``member`` with seeded random weights, saved as a checkpoint."""
    import torch

    from spk2img.training.checkpoint import config_to_dict, save_checkpoint
    from spk2img.training.network import build_model

    torch.manual_seed(INIT_SEED)
    model = build_model(member)
    path = directory / f"{member}-random.pt"
    save_checkpoint(path, config=config_to_dict(model.config), model=model.state_dict())
    return Weights(member, path, trained=False)


def shipped() -> Weights | None:
    """The shipped default model, if this installation has both of its files."""
    from spk2img.core.onnx_backend import default_model_path
    from spk2img.training.predictor import DEFAULT_CHECKPOINT

    onnx = default_model_path()
    if not (onnx.is_file() and DEFAULT_CHECKPOINT.is_file()):
        return None
    return Weights("shipped", DEFAULT_CHECKPOINT, trained=True, onnx=onnx)


def net_rows(weights: Weights, directory: Path) -> tuple[list[NetRow], dict[str, str]]:
    """A row per backend of :data:`~spk2img.bench.rows.BACKENDS` for ``weights``, exporting the
    ONNX graphs into ``directory``; and the backends whose export failed, with the reason."""
    rows, failed = [], {}
    for backend in BACKENDS:
        path = weights.checkpoint
        if backend == "onnx" and weights.onnx is not None:
            path = weights.onnx
        elif backend != "torch":
            path = directory / f"{weights.name}-{backend}.onnx"
            try:
                export_backend(weights.checkpoint, backend, path)
            except Exception as exc:  # noqa: BLE001 - the row reports the failure
                failed[backend] = f"{type(exc).__name__}: {exc}"
                continue
        rows.append(NetRow(weights.name, backend, str(path), weights.trained))
    return rows, failed


def export_backend(checkpoint: Path, backend: str, path: Path) -> None:
    """Export ``checkpoint`` as the ONNX graph ``backend`` runs (with :mod:`spk2img.export`)."""
    from spk2img.export import export

    variant = {"onnx": {}, "onnx-deform": {"deform_conv": True},
               "onnx-int8": {"precision": "int8"}, "onnx-fp16": {"precision": "fp16"}}  # fmt: skip
    export(checkpoint, path, **variant[backend])


def cost(weights: Weights, sizes: dict[str, tuple[int, int]]) -> dict:
    """``params`` and ``macs`` per frame at each named ``(height, width)`` of ``sizes``."""
    import torch

    from spk2img.training.checkpoint import config_from_dict, load_checkpoint
    from spk2img.training.complexity import count_macs, count_parameters
    from spk2img.training.network import build_model

    config = config_from_dict(load_checkpoint(weights.checkpoint)["config"])
    with torch.device("meta"):
        params = count_parameters(build_model(config))
    macs = {name: count_macs(config, h, w) for name, (h, w) in sizes.items()}
    return {"params": params, "macs": macs}
