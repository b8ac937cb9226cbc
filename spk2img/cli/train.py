"""``spk2img train``: train a Spk2ImgNet member on simulated streams (needs the train extra).

Run under ``torchrun --nproc_per_node N -m spk2img train …`` for data parallelism (gloo on CPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from spk2img.cli.extras import needs_extra
from spk2img.errors import InputError


def _fields():
    from spk2img.training.train import TrainConfig

    return TrainConfig, dataclasses.fields(TrainConfig)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train a model on simulated spike streams", description=__doc__
    )
    # the flags mirror TrainConfig; their defaults are filled in at run time so that the
    # parser can be built without importing torch
    for name, kind in [
        ("member", str),
        ("run-dir", str),
        ("steps", int),
        ("batch-size", int),
        ("patch", int),
        ("lr", float),
        ("warmup-steps", int),
        ("loss", str),
        ("seed", int),
        ("data-mix", str),
        ("sensor-preset", str),
        ("ideal-share", float),
        ("workers", int),
        ("device", str),
        ("val-every", int),
        ("val-per-class", int),
        ("checkpoint-every", int),
        ("threads", int),
        ("log-every", int),
        ("init", str),
    ]:
        p.add_argument(f"--{name}", type=kind, default=None)
    p.add_argument(
        "--data",
        action="append",
        metavar="DIR",
        help="a folder of photographs and clips to train on (repeatable)",
    )
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (there is none either when stderr is not a terminal)",
    )


def run(args: argparse.Namespace) -> int:
    with needs_extra("train", "training"):
        config_cls, fields = _fields()
    from spk2img.model.config import MEMBERS
    from spk2img.training.data import DataMix
    from spk2img.training.train import train

    values = {
        f.name: getattr(args, f.name) for f in fields if getattr(args, f.name, None) is not None
    }
    if args.no_progress or not sys.stderr.isatty():
        values["progress"] = False
    try:
        cfg = config_cls(**values)
        DataMix.parse(cfg.data_mix)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    if cfg.member not in MEMBERS:
        raise InputError(f"unknown member {cfg.member!r}: choose one of {', '.join(MEMBERS)}")
    train(cfg)
    return 0
