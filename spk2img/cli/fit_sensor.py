"""``spk2img fit-sensor``: estimate a real sensor's noises from a capture of a still scene and
write them as a sensor preset (JSON) that ``spk2img simulate --sensor`` and ``spk2img train
--sensor-preset`` load. The estimators: docs/sensor.md."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from spk2img.errors import InputError
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, as_spike_array, read_spikes
from spk2img.sim.sensor_fit import fit_sensor, save_preset


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit-sensor",
        help="estimate a sensor preset from a real capture of a still scene",
        description=__doc__,
    )
    p.add_argument("capture", type=Path, metavar="CAPTURE", help=".dat, .npy or .npz spikes")
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height (.dat only)")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width (.dat only)")
    p.add_argument("--out", type=Path, help="preset to write (default: print it only)")


def run(args: argparse.Namespace) -> int:
    spikes = read_spikes(args.capture, args.height, args.width)
    frames = as_spike_array(np.asarray(spikes[0 : spikes.shape[0]]))
    try:
        sensor, report = fit_sensor(frames)
    except ValueError as exc:
        raise InputError(f"{args.capture}: {exc}") from exc
    print(json.dumps({"sensor": asdict(sensor), "report": report}, indent=2))
    if args.out is not None:
        save_preset(args.out, sensor, report, source=args.capture.name)
    return 0
