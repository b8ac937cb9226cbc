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
"""Seed of the family members' random weights (:func:`spk2img.export.onnx_export.random_source`)."""
PRECISIONS = {"onnx-int8": "int8", "onnx-fp16": "fp16"}
"""Reduced-precision backends and their :mod:`spk2img.export.quantize` precision."""


@dataclass(frozen=True)
class Weights:
    """One set of network weights to benchmark."""

    name: str
    """Row label: a member name (``tiny``) or a trained model's name (``shipped``)."""
    checkpoint: Path
    """The checkpoint (config and weights, :mod:`spk2img.model.checkpoint`)."""
    trained: bool
    """Whether the weights were trained (untrained ones are timed but never scored)."""
    onnx: Path | None = None
    """An existing grid_sample ONNX graph of these weights (the shipped one), else exported."""
    random_member: str | None = None
    """The member whose seeded random weights these are (``None``: a trained checkpoint)."""

    def describe(self) -> str:
        """One line for the report: the name and where the weights come from."""
        if self.random_member is not None:
            return f"{self.name} (random weights, seed {INIT_SEED}; untrained)"
        return f"{self.name} (trained, `{self.checkpoint.name}`)"

    def export_source(self):
        """The :class:`~spk2img.export.onnx_export.ExportSource` of these weights."""
        from spk2img.export.onnx_export import checkpoint_source, random_source

        if self.random_member is not None:
            return random_source(self.random_member, seed=INIT_SEED)
        return checkpoint_source(self.checkpoint)


def random_member(member: str, directory: Path) -> Weights:
    """Family member ``member`` with the exporter's seeded random weights, also saved as a
    checkpoint for the PyTorch row (so that every backend runs the very same weights)."""
    from spk2img.model.checkpoint import config_to_dict, save_checkpoint

    weights = Weights(member, directory / f"{member}-random.pt", False, random_member=member)
    model = weights.export_source().model
    save_checkpoint(
        weights.checkpoint, config=config_to_dict(model.config), model=model.state_dict()
    )
    return weights


def shipped() -> Weights | None:
    """The shipped default model, if this installation has both of its files."""
    from spk2img.runtime.onnx_backend import default_model_path
    from spk2img.runtime.torch_backend import DEFAULT_CHECKPOINT

    onnx = default_model_path()
    if not (onnx.is_file() and DEFAULT_CHECKPOINT.is_file()):
        return None
    return Weights("shipped", DEFAULT_CHECKPOINT, trained=True, onnx=onnx)


def net_rows(
    weights: Weights, directory: Path, backends: tuple[str, ...] = tuple(BACKENDS)
) -> tuple[list[NetRow], dict[str, str]]:
    """A row per backend of ``backends`` (:data:`~spk2img.bench.rows.BACKENDS`) for ``weights``,
    with the ONNX graphs made in ``directory``; and the backends whose graph could not be made,
    with why.

    The fp32 graphs come from :func:`~spk2img.export.pipeline.export_verified` (export, then
    torch parity); the int8 and fp16 ones from
    :func:`~spk2img.export.quantize.reduce_precision` of the fp32 grid_sample graph (the
    benchmark measures their error itself); the self-ensemble runs that fp32 graph.
    """
    paths = {"torch": weights.checkpoint} if "torch" in backends else {}
    failed = {}
    for backend in backends:
        if backend == "torch":
            continue
        path = directory / f"{weights.name}-{backend}.onnx"
        try:
            if backend == "onnx" and weights.onnx is not None:
                path = weights.onnx
            elif backend == "onnx-ensemble":  # the onnx row's graph, four calls a frame
                if "onnx" not in paths:
                    raise RuntimeError("the self-ensemble runs the onnx row's graph: none made")
                path = paths["onnx"]
            else:
                make_graph(weights, backend, path, paths.get("onnx"))
        except Exception as exc:  # noqa: BLE001 - the row reports the failure
            failed[backend] = f"{type(exc).__name__}: {exc}"
            continue
        paths[backend] = path
    rows = [NetRow(weights.name, b, str(path), weights.trained) for b, path in paths.items()]
    return rows, failed


def make_graph(
    weights: Weights,
    backend: str,
    path: Path,
    fp32_graph: Path | None,
    block_graphs: bool = False,
) -> None:
    """Write the ONNX graph ``backend`` runs to ``path``; ``fp32_graph`` is the grid_sample
    graph that reduced-precision variants start from; ``block_graphs``: the encoder and head
    beside it too (for streamed rows)."""
    from spk2img.export.onnx_export import ExportConfig
    from spk2img.export.pipeline import export_verified
    from spk2img.export.quantize import reduce_precision

    if backend in PRECISIONS:
        if fp32_graph is None:
            raise RuntimeError("no fp32 grid_sample graph to start from")
        reduce_precision(fp32_graph, path, PRECISIONS[backend])
        return
    graph = "deform_conv" if backend == "onnx-deform" else "grid_sample"
    # the CPU rows run one-shot graphs; the shipped model streams with its own block graphs
    config = ExportConfig(graph=graph)
    export_verified(weights.export_source(), path, config, block_graphs=block_graphs)


def cost(weights: Weights, sizes: dict[str, tuple[int, int]]) -> dict:
    """``params`` and ``macs`` per frame at each named ``(height, width)`` of ``sizes``."""
    import torch

    from spk2img.model.checkpoint import load_checkpoint, stored_config
    from spk2img.model.complexity import count_macs, count_parameters
    from spk2img.model.network import build_model

    config = stored_config(load_checkpoint(weights.checkpoint), weights.checkpoint)
    with torch.device("meta"):
        params = count_parameters(build_model(config))
    macs = {name: count_macs(config, h, w) for name, (h, w) in sizes.items()}
    return {"params": params, "macs": macs}
