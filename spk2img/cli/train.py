"""``spk2img train``: train a Spk2ImgNet member on simulated streams (needs the train extra).

Run under ``torchrun --nproc_per_node N -m spk2img train …`` for data parallelism (gloo on CPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
from pathlib import Path

from spk2img.cli.extras import needs_extra
from spk2img.errors import InputError
from spk2img.training.config import TrainConfig

NOT_FLAGS = ("data", "progress")
"""Fields set by flags of their own: ``--data DIR`` (repeatable) and ``--no-progress``."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a model on simulated spike streams",
        description=__doc__,
    )
    # the flags mirror TrainConfig; they default to None so that only the flags given override
    # the config (a resumed run keeps its own); the help shows the config's defaults
    for f in dataclasses.fields(TrainConfig):
        if f.name in NOT_FLAGS:
            continue
        choices = f.metadata["choices"]  # checked by TrainConfig, with its own messages
        among = f"choices: {', '.join(choices)}; " if choices else ""
        p.add_argument(
            f"--{f.name.replace('_', '-')}",
            type=type(f.default),
            default=None,
            metavar=f.name.upper(),
            help=f"{f.metadata['help']} ({among}default: {f.default})",
        )
    p.add_argument(
        "--data",
        action="append",
        metavar="DIR",
        help="a folder of photographs and clips to train on (repeatable; none: procedural "
        "scenes only)",
    )
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (there is none either when stderr is not a terminal)",
    )


def run(args: argparse.Namespace) -> int:
    with needs_extra("train", "training"):
        from spk2img.training.train import train
    from spk2img.training.data import DataMix, speed_weights

    fields = dataclasses.fields(TrainConfig)
    values = {
        f.name: getattr(args, f.name) for f in fields if getattr(args, f.name, None) is not None
    }
    if args.no_progress or not sys.stderr.isatty():
        values["progress"] = False
    try:
        cfg = TrainConfig(**values)
        DataMix.parse(cfg.data_mix)
        speed_weights(cfg.speed_mix)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    summary = train(cfg)
    if summary["stopped"]:
        name, step = summary["stopped"]["signal"], summary["stopped"]["step"]
        print(
            f"spk2img train: stopped at step {step} of {cfg.steps} ({name}); "
            f"{Path(cfg.run_dir) / 'last.pt'} holds it: the same command continues the run",
            file=sys.stderr,
        )
        return 128 + signal.Signals[name].value if name in signal.Signals.__members__ else 130
    if summary["last_validation"]:
        last = summary["last_validation"]
        best = summary["best_checkpoint"] or "not kept (its log's best was not beaten since)"
        print(
            f"trained {cfg.member} to step {summary['steps']} in {summary['wall_s'] / 3600:.2f} h "
            f"of optimiser steps; best checkpoint {best} "
            f"({summary['val_set']} validation, {summary['best_psnr']:.2f} dB); last validation: "
            f"procedural {last['psnr']:.2f} dB"
            + (f", natural {last['natural']['psnr']:.2f} dB" if "natural" in last else "")
            + (f", real video {last['real_video']['psnr']:.2f} dB" if "real_video" in last else ""),
            file=sys.stderr,
        )
    return 0
