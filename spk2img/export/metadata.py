"""The ``metadata_props`` an exported graph carries, and the weights' fingerprint.

Keys (all values are strings, as ONNX requires):

- ``name``: the model's name (``spk2img-<member>``, or the checkpoint's stem).
- ``version``: the spk2img package version that exported it.
- ``member`` and ``config``: the family member and its :class:`Spk2ImgNetConfig` as JSON.
- ``window`` (41 as published) and ``rate`` (0.6): the spike frames read (the config's
  geometry, :meth:`~spk2img.model.config.Geometry.from_metadata`) and the spikes per frame at I = 1
  (docs/format.md, docs/architecture.md); the output is linear intensity ``I`` in [0, 1].
- ``training_commit`` and ``training_commit_source``: the commit the checkpoint was trained at
  when the checkpoint stores one (``source`` = ``checkpoint``), else the exporting tree's
  ``git rev-parse HEAD`` (``git HEAD at export``), else ``unknown``.
- ``weights_sha256``: :func:`weights_sha256` of the network's ``state_dict``.
- ``source``: the checkpoint's file name and training step, or ``random weights, seed N``
  (then also ``random_seed``: such a graph's weights can be rebuilt from member and seed).
- ``sensors``: the sensor regimes the weights were trained on (:func:`trained_sensors`;
  absent for random weights): which streams the model is for.
- ``graph`` (``grid_sample`` or ``deform_conv``: how the deformable sampling is expressed) and
  ``opset``, set by the exporter; ``precision``: ``fp32``, ``fp16`` or ``int8``, and for the
  last two ``precision_report`` (JSON: error against fp32 and ground truth, see
  :func:`spk2img.export.quantize.precision_report`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping

import torch

from spk2img import __version__
from spk2img.io.light import SPIKE_RATE
from spk2img.model.checkpoint import config_to_dict
from spk2img.model.network import Spk2ImgNet
from spk2img.provenance import git_commit

UNKNOWN = "unknown"


def weights_sha256(state_dict: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 (hex) of a ``state_dict``, independent of how it was saved.

    Entries are taken in ascending order of their keys (Python string order); each contributes
    the key in UTF-8, a NUL byte, ``<dtype>[<d0>,<d1>,...]`` (e.g. ``float32[64,4,3,3]``,
    numpy dtype names), a NUL byte, then the tensor's values as C-order little-endian bytes.
    """
    digest = hashlib.sha256()
    for key in sorted(state_dict):
        array = state_dict[key].detach().cpu().contiguous().numpy()
        shape = ",".join(str(d) for d in array.shape)
        digest.update(f"{key}\0{array.dtype.name}[{shape}]\0".encode())
        digest.update(array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes("C"))
    return digest.hexdigest()


def training_commit(checkpoint: Mapping | None) -> tuple[str, str]:
    """``(commit, where it came from)``: the checkpoint's ``commit`` entry (top level, as
    ``spk2img train`` writes it, or in its ``train_config``), else ``git rev-parse HEAD`` of the
    tree this package lives in, else ``unknown``."""
    state = checkpoint or {}
    for holder in (state, state.get("train_config") or {}):
        if holder.get("commit") not in (None, "", UNKNOWN):
            return str(holder["commit"]), "checkpoint"
    commit = git_commit()
    return (commit, "git HEAD at export") if commit != UNKNOWN else (UNKNOWN, UNKNOWN)


def trained_sensors(checkpoint: Mapping) -> str:
    """The sensor regimes a checkpoint's run trained on, in words: on natural data (``--data``)
    the noise-free and the fitted real-camera sensor at its ``ideal_share``; on procedural scenes
    only, :meth:`~spk2img.sim.simulator.SensorConfig.random`'s draws."""
    train_config = checkpoint.get("train_config") or {}
    if not train_config.get("data"):
        return "random (procedural scenes only)"
    share = float(train_config.get("ideal_share", 0.5))
    if share == 1:
        return "noise-free"
    if share == 0:
        return "fitted real camera"
    return f"noise-free {share:.0%}, fitted real camera {1 - share:.0%}"


def model_metadata(
    model: Spk2ImgNet, name: str, member: str, source: str, checkpoint: Mapping | None
) -> dict[str, str]:
    """The ``metadata_props`` of an fp32 export of ``model`` (``graph`` is set by the exporter).

    ``checkpoint`` is the loaded checkpoint dict (for its commit), or None for random weights.
    """
    commit, commit_source = training_commit(checkpoint)
    sensors = {"sensors": trained_sensors(checkpoint)} if checkpoint else {}
    return {
        "name": name,
        "version": __version__,
        "member": member,
        "config": json.dumps(config_to_dict(model.config), sort_keys=True),
        "window": str(model.config.window_frames),
        "rate": str(SPIKE_RATE),
        "training_commit": commit,
        "training_commit_source": commit_source,
        "weights_sha256": weights_sha256(model.state_dict()),
        "source": source,
        "precision": "fp32",
    } | sensors
