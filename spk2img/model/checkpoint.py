"""Training checkpoints: plain tensors and containers, loadable with ``weights_only=True``."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch

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


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint with ``weights_only=True`` (no arbitrary code is unpickled)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such checkpoint: {path}")
    return torch.load(path, map_location="cpu", weights_only=True)


def load_model(path: str | Path) -> Spk2ImgNet:
    """The network stored in a checkpoint (its config and weights), in eval mode."""
    state = load_checkpoint(path)
    model = Spk2ImgNet(config_from_dict(state["config"]))
    model.load_state_dict(state["model"])
    return model.eval()


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
)


def release_checkpoint(src: str | Path, dst: str | Path) -> None:
    """Copy a training checkpoint without its optimiser state (what the repo ships)."""
    state = load_checkpoint(src)
    save_checkpoint(dst, **{k: state[k] for k in RELEASE_KEYS if k in state})
