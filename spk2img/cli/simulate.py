"""``spk2img simulate``: a random scene filmed by a simulated spike camera -> ``OUT.dat`` and
``OUT.gt.npz`` (``gt`` float32 ``(T, H, W)``, the intensity in the middle of every frame, and
``meta``, a JSON string of the scene and sensor parameters). Both are written in chunks, so
memory stays bounded however many frames are asked for."""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from spk2img.cli.progress import add_progress_flags, progress_bar, say
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, MAX_SIDE, pack_frames
from spk2img.sim.scenes import BRIGHTNESSES, MOTIONS, random_scene
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.simulator import SensorConfig, SpikeSimulator, ground_truth

SENSORS = {
    "ideal": SensorConfig.ideal,
    "real": SensorConfig.real,
    "fitted": lambda: load_preset(FITTED_PRESET),
}
CHUNK_FRAMES = 32


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a spike stream (.dat) and its ground truth",
        description="Film a random scene with a simulated spike camera: write OUT.dat "
        "(docs/format.md) "
        "and OUT.gt.npz with 'gt' (T, H, W) float32, the linear intensity at the middle of each "
        "frame, and 'meta', a JSON string of the scene and sensor parameters.",
    )
    p.add_argument("out", type=Path, metavar="OUT.dat", help="spike stream to write")
    p.add_argument("--frames", type=int, default=400, help="frames to simulate (default 400)")
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height (px)")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width (px)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--motion", choices=MOTIONS, help="motion class (default: random)")
    p.add_argument("--brightness", choices=BRIGHTNESSES, help="brightness class (default: random)")
    p.add_argument(
        "--sensor",
        choices=tuple(SENSORS),
        default="ideal",
        help="ideal (noise-free), real (typical noises) or fitted (fitted to a real PKU capture, "
        "docs/sensor.md); default: ideal",
    )
    add_progress_flags(p)


def run(args: argparse.Namespace) -> int:
    problem = _check(args)
    if problem:
        print(f"spk2img simulate: error: {problem}", file=sys.stderr)
        return 2
    gt_path = args.out.with_suffix(".gt.npz")
    rng = np.random.default_rng(args.seed)
    scene = random_scene(rng, args.height, args.width, args.motion, args.brightness)
    sensor = SENSORS[args.sensor]()
    simulator = SpikeSimulator(scene, sensor, rng)
    meta = {
        "frames": args.frames,
        "height": args.height,
        "width": args.width,
        "seed": args.seed,
        "substeps": simulator.substeps,
        "gt": "gt[k] = scene intensity at t = k + 0.5, the middle of frame k",
        "scene": scene.meta,
        "sensor": {"preset": args.sensor, **asdict(sensor)},
    }
    shape = (args.frames, args.height, args.width)
    # written under temporary names and renamed at the end: a stopped run leaves no truncated
    # stream that would read as a shorter one
    tmp_dat, tmp_gt = (path.with_name(path.name + ".partial") for path in (args.out, gt_path))
    try:
        with (
            tmp_dat.open("wb") as dat,
            zipfile.ZipFile(tmp_gt, "w", allowZip64=True) as npz,
            progress_bar(args, total=args.frames) as bar,
        ):
            npz.writestr("meta.npy", _npy_bytes(np.array(json.dumps(meta))))
            with npz.open("gt.npy", "w", force_zip64=True) as gt:  # streamed: no (T, H, W) array
                _write_stream(dat, gt, simulator, shape, bar)
        os.replace(tmp_gt, gt_path)
        os.replace(tmp_dat, args.out)
    except OSError as exc:
        print(
            f"spk2img simulate: error: cannot write {args.out} / {gt_path}: {exc}", file=sys.stderr
        )
        return 1
    finally:
        tmp_dat.unlink(missing_ok=True)
        tmp_gt.unlink(missing_ok=True)
    say(
        args,
        f"wrote {args.frames} frames of {args.height}x{args.width} to {args.out} and {gt_path}",
    )
    return 0


def _write_stream(dat, gt, simulator: SpikeSimulator, shape: tuple, bar) -> None:
    """Simulate ``shape = (T, H, W)`` chunk by chunk into the open ``.dat`` and ``gt.npy``."""
    np.lib.format.write_array_header_1_0(
        gt, {"descr": "<f4", "fortran_order": False, "shape": shape}
    )
    for start in range(0, shape[0], CHUNK_FRAMES):
        frames = range(start, min(start + CHUNK_FRAMES, shape[0]))
        dat.write(pack_frames(simulator.run(len(frames))))
        gt.write(ground_truth(simulator.scene, frames).astype("<f4").tobytes())
        bar.update(len(frames))


def _check(args: argparse.Namespace) -> str | None:
    """What is wrong with the arguments, in one line, or None."""
    if args.frames < 1:
        return f"--frames must be >= 1, got {args.frames}"
    if not (1 <= args.height <= MAX_SIDE and 1 <= args.width <= MAX_SIDE):
        return f"--height and --width must be from 1 to {MAX_SIDE}, got {args.height}x{args.width}"
    if args.seed < 0:
        return f"--seed must be >= 0, got {args.seed}"
    if args.out.suffix.lower() != ".dat":
        return f"OUT must name a .dat file, got {args.out}"
    if not args.out.parent.is_dir():
        return f"no such directory: {args.out.parent}"
    return None


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()
