"""Training checkpoints: plain tensors and containers, loadable with ``weights_only=True``."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from pickle import UnpicklingError

import torch

from spk2img.errors import InputError

from .config import Spk2ImgNetConfig
from .network import Spk2ImgNet


def config_to_dict(config: Spk2ImgNetConfig) -> dict:
    return {
        k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(config).items()
    }


RETIRED_FIELDS = {"intensity_base": False}
"""Config fields of earlier versions, with the value under which they built today's network."""


def config_from_dict(data: dict) -> Spk2ImgNetConfig:
    """The config a checkpoint stores; a retired field is dropped where its value is the one
    that builds today's network, and refused (``ValueError``) where it is not."""
    data = dict(data)
    for name, neutral in RETIRED_FIELDS.items():
        if name in data and data.pop(name) != neutral:
            raise ValueError(
                f"the checkpoint's network has {name}, which this spk2img no longer builds"
            )
    known = {f.name for f in dataclasses.fields(Spk2ImgNetConfig)}
    if unknown := sorted(set(data) - known):
        raise ValueError(
            f"the checkpoint's config has fields this spk2img does not know: {unknown}"
        )
    return Spk2ImgNetConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def save_checkpoint(path: str | Path, **state) -> None:
    """Write ``state`` atomically (a temporary file, then renamed): a kill never corrupts it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


class CheckpointError(InputError):
    """A file that is not a spk2img training checkpoint this version can read (missing,
    corrupt, or holding a network it does not build)."""


def _not_a_checkpoint(path: str | Path, exc: BaseException) -> CheckpointError:
    first_line = (str(exc).strip().splitlines() or [""])[0][:120]
    reason = f"{type(exc).__name__}: {first_line}"
    return CheckpointError(f"{path}: not a spk2img training checkpoint ({reason})")


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint with ``weights_only=True`` (no arbitrary code is unpickled);
    :class:`CheckpointError` when ``path`` is missing or torch cannot read it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no such checkpoint: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, UnpicklingError) as exc:
        raise _not_a_checkpoint(path, exc) from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not a spk2img training checkpoint (no state dict)")
    return state


def stored_config(state: dict, path: str | Path) -> Spk2ImgNetConfig:
    """The config of the network checkpoint ``state`` (read from ``path``) stores;
    :class:`CheckpointError` when it has none or one this spk2img cannot build."""
    try:
        return config_from_dict(state["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise _not_a_checkpoint(path, exc) from exc


def load_weights(model: Spk2ImgNet, state: dict, path: str | Path) -> None:
    """Copy checkpoint ``state``'s weights into ``model`` (built from :func:`stored_config`);
    :class:`CheckpointError` when they are missing or do not fit it."""
    try:
        model.load_state_dict(state["model"])
    except (KeyError, RuntimeError, TypeError) as exc:
        raise _not_a_checkpoint(path, exc) from exc


def read_network(path: str | Path) -> tuple[Spk2ImgNet, dict]:
    """The network a checkpoint stores (its config and weights, in eval mode) and the whole
    stored state; :class:`CheckpointError` for anything that is not such a checkpoint."""
    state = load_checkpoint(path)
    model = Spk2ImgNet(stored_config(state, path))
    load_weights(model, state, path)
    return model.eval(), state


def load_model(path: str | Path) -> Spk2ImgNet:
    """The network stored in a checkpoint, in eval mode (:func:`read_network`)."""
    return read_network(path)[0]


RELEASE_KEYS = (
    "model",
    "config",
    "member",
    "step",
    "wall_s",
    "train_config",
    "val_psnr",
    "val_set",
    "commit",
    "hardware",
    "init_from",
    "averaged_from",
    "weights",
)


def release_checkpoint(
    src: str | Path,
    dst: str | Path,
    dtype: torch.dtype | None = None,
    val_set: str | None = None,
) -> None:
    """Copy a training checkpoint without its optimiser state (what the repo ships); with
    ``dtype`` (``torch.float16`` for a larger member's committed weights: half the bytes) its
    floating-point weights are stored in that type, and loading casts them back to the
    network's. ``val_set``, when given, replaces the run's record of what the checkpoint was
    chosen on and drops its logged score (``val_psnr``, on the run's own set): a step chosen
    after the run, e.g. ``"real video frames"`` for the whole-frame real-video validation."""
    state = load_checkpoint(src)
    release = {k: state[k] for k in RELEASE_KEYS if k in state}
    if val_set is not None:
        release.pop("val_psnr", None)
        release["val_set"] = val_set
    if dtype is not None:
        release["model"] = {
            name: tensor.to(dtype) if tensor.is_floating_point() else tensor
            for name, tensor in release["model"].items()
        }
    save_checkpoint(dst, **release)


def average_checkpoints(
    sources: list[str | Path],
    weights: list[float],
    dst: str | Path,
    val_set: str | None = None,
) -> None:
    """Write to ``dst`` a release checkpoint whose network weights are the weighted mean of the
    ``sources``' (same config; ``weights`` positive, summing to 1): a "model soup" of one
    lineage's checkpoints. Everything else is the last source's but its validation score
    (``val_psnr``: not the mean's), plus ``averaged_from`` (each
    source's file name, step and weight; a source that is itself a mean is listed as what it
    averages, its weights scaled by its own). ``val_set``, when given, replaces the last source's
    record of what the checkpoint was chosen on (a mean is chosen after the runs, on a score
    none of them logged: ``"real video frames"`` for the whole-frame real-video validation).
    :class:`CheckpointError` when a source is not a checkpoint or the configs differ;
    :class:`InputError` for bad weights."""
    if len(sources) < 2 or len(weights) != len(sources):
        raise InputError(
            f"need two or more checkpoints and one weight each, got {len(sources)} "
            f"checkpoints and {len(weights)} weights"
        )
    if min(weights) <= 0 or abs(sum(weights) - 1) > 1e-6:
        raise InputError(f"weights must be positive and sum to 1, got {weights}")
    networks, states = zip(*(read_network(path) for path in sources), strict=True)
    for network, path in zip(networks[1:], sources[1:], strict=True):
        if network.config != networks[0].config:
            raise CheckpointError(f"{path}: a different network from {sources[0]}'s")
    last = states[-1]
    # not val_psnr: the last source's validation score is not the mean's
    release = {k: last[k] for k in RELEASE_KEYS if k in last and k != "val_psnr"}
    if val_set is not None:
        release["val_set"] = val_set
    release["model"] = {}
    for name, tensor in last["model"].items():
        if tensor.is_floating_point():
            terms = [w * s["model"][name].double() for w, s in zip(weights, states, strict=True)]
            tensor = sum(terms).to(tensor.dtype)
        release["model"][name] = tensor
    release["averaged_from"] = [
        part
        for path, state, w in zip(sources, states, weights, strict=True)
        for part in _constituents(path, state, w)
    ]
    save_checkpoint(dst, **release)


def _constituents(path: str | Path, state: dict, weight: float) -> list[dict]:
    """What a checkpoint of weight ``weight`` in a mean contributes to its ``averaged_from``
    record: itself, or, for a mean, its own sources with their weights times ``weight``."""
    if "averaged_from" not in state:
        return [{"path": Path(path).name, "step": state.get("step"), "weight": weight}]
    return [{**part, "weight": part["weight"] * weight} for part in state["averaged_from"]]
