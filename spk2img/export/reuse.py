"""Export without tracing: graphs already traced for the same architecture, given new weights.

Tracing is nearly all of an export's time (30-70 s a graph on a 2-core CPU, three graphs with
the block encoder and head) and depends only on the architecture, not on the weights. The
shipped models' graphs were traced from the same network code, so a checkpoint of the same
config (a fine-tuned ``default``, say) needs only their graphs with its weights written over
theirs. :func:`spk2img.export.pipeline.export_verified` checks such graphs against PyTorch
exactly as it checks traced ones, and traces after all where they fail.

A weight is found in a template graph by name (the initializer ``model.<key>`` of its
state-dict key) or, where the exporter folded it into a constant of another name (a PReLU
slope reshaped to ``(1, 1, 1, 1)`` for broadcasting), by value: the template's own checkpoint
beside it (``<stem>.pt``, checked against the graph's ``weights_sha256``) says which constant
holds which weight.
"""

from __future__ import annotations

import json
from pathlib import Path

import onnx

from spk2img.model.checkpoint import config_from_dict, read_network
from spk2img.runtime.block_codec import block_graph_paths
from spk2img.runtime.onnx_backend import shipped_models

from .metadata import weights_sha256
from .onnx_export import (
    ExportConfig,
    ExportSource,
    finish_graph,
    graph_io,
    graph_props,
    weight_arrays,
    write_weights,
)

MATCHED_PROPS = ("config", "version")
"""Metadata a template must share with the network it lends its graphs to (besides the graph
kind and opset of the export)."""


def find_template(source: ExportSource, config: ExportConfig, block_graphs: bool) -> Path | None:
    """A shipped fp32 one-shot graph whose traced graphs ``source`` can take: the same network
    config and spk2img version, ``config``'s graph kind and opset, its checkpoint beside it, and
    (``block_graphs``) its encoder and head beside it; None if no shipped model qualifies."""
    wanted = {key: source.metadata[key] for key in MATCHED_PROPS}
    wanted |= {"graph": config.graph, "opset": str(config.opset), "precision": "fp32"}
    for path in shipped_models().values():
        beside = [path.with_suffix(".pt")]
        if block_graphs:
            beside += block_graph_paths(path).values()
        if not all(p.is_file() for p in beside):
            continue
        props = graph_props(onnx.load(path, load_external_data=False))
        if all(_same(key, props.get(key), value) for key, value in wanted.items()):
            return path
    return None


def _same(key: str, stored: str | None, wanted: str) -> bool:
    """Whether a template's metadata value fits; configs are compared as configs, so that a
    field added since (at its default) does not make a same network another."""
    if key == "config" and stored is not None:
        return config_from_dict(json.loads(stored)) == config_from_dict(json.loads(wanted))
    return stored == wanted


def reuse_graphs(
    template: Path, source: ExportSource, out: Path, config: ExportConfig, block_graphs: bool
) -> bool:
    """Write ``template``'s graphs (its block graphs too if ``block_graphs``) with ``source``'s
    weights and metadata to ``out`` (and beside it), each checked as a traced graph is
    (:func:`~spk2img.export.onnx_export.finish_graph`). Returns False, writing nothing, where a
    template graph does not hold its own checkpoint's weights or a weight cannot be told apart
    from another by value."""
    own, _ = read_network(template.with_suffix(".pt"))
    own_hash = weights_sha256(own.state_dict())
    old = weight_arrays(own.state_dict())
    new = weight_arrays(source.model.state_dict())
    if old.keys() != new.keys():
        return False
    parts = {None: (template, out)}
    if block_graphs:
        targets = block_graph_paths(out)
        parts |= {part: (path, targets[part]) for part, path in block_graph_paths(template).items()}
    graphs = {}
    for part, (path, target) in parts.items():
        graph = onnx.load(path)
        if graph_props(graph).get("weights_sha256") != own_hash:
            return False
        if write_weights(graph, old, new) is None:
            return False
        graphs[part] = (graph, target)
    for part, (graph, target) in graphs.items():
        metadata = source.metadata | ({} if part is None else {"part": part})
        finish_graph(graph, metadata, config, target, graph_io(graph))
    return True
