"""Samples per second of training with each spike simulator, side by side in one run.

``python scripts/synthesis_speed.py [--data DATA] [--member small] [--batch-size 16] [--patch 48]
[--device cpu] [--workers 1] [--steps 12] [--precisions fp32,bf16] [--json
docs/synthesis_speed.json]`` measures, on one device, in one process:

- **synthesis alone**, in this process (one thread): training samples a second that the numpy
  simulator makes (``SampleMaker.batch``, what a worker process does today), and that torch
  synthesis makes (``SampleMaker.plans`` in a worker, ``film_plans`` on the device), with the
  time each of its two parts takes;
- **training**: ``spk2img train`` for ``--steps`` optimiser steps with ``--synthesis numpy``,
  then with ``--synthesis torch``, in each of ``--precisions`` (``spk2img train --precision``:
  fp32, bf16 autocast), the same member, batch, patch, data and workers; samples a second are
  the median over its logged intervals after the first (warm-up).

The JSON holds every figure with the device, threads and workers.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import torch

from spk2img.evaluation.natural_validation import NEVER_TRAINED
from spk2img.hardware import cpu_words
from spk2img.model.config import get_config
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.sources import SourceIndex
from spk2img.training.config import TrainConfig
from spk2img.training.data import DataMix, SampleMaker
from spk2img.training.synthesis import batch_generator, film_plans
from spk2img.training.train import train


def synthesis_rates(args, device: torch.device) -> dict:
    """Samples a second of each simulator alone, in this process."""
    index = SourceIndex.scan(args.data, args.patch, NEVER_TRAINED) if args.data else None
    maker = SampleMaker(
        args.patch,
        seed=1,
        mix=DataMix.parse(TrainConfig.data_mix),
        index=index,
        real_sensor=load_preset(FITTED_PRESET),
        ideal_share=1.0,
        geometry=get_config(args.member).geometry,
        display_share=0.5,
    )
    maker.batch(0, args.batch_size)  # warm the source caches for both
    maker.plans(0, args.batch_size)
    steps = range(1, 1 + args.synthesis_batches)
    t0 = time.perf_counter()
    for step in steps:
        maker.batch(step, args.batch_size)
    numpy_s = time.perf_counter() - t0
    plan_s = film_s = 0.0
    for step in steps:
        t0 = time.perf_counter()
        plans = maker.plans(step, args.batch_size)
        t1 = time.perf_counter()
        spikes, _ = film_plans(plans, maker.geometry, batch_generator(1, 0, step, device))
        if device.type == "cuda":
            torch.cuda.synchronize()
        plan_s, film_s = plan_s + t1 - t0, film_s + time.perf_counter() - t1
    samples = len(steps) * args.batch_size
    return {
        "numpy_samples_per_s": samples / numpy_s,
        "torch_plans_samples_per_s": samples / plan_s,
        "torch_film_samples_per_s": samples / film_s,
        "torch_samples_per_s": samples / (plan_s + film_s),
    }


def training_rate(args, synthesis: str, precision: str, run_dir: Path) -> float:
    """Median training samples a second of a short ``spk2img train`` run."""
    cfg = TrainConfig(
        member=args.member,
        run_dir=str(run_dir),
        steps=args.steps,
        batch_size=args.batch_size,
        patch=args.patch,
        data=args.data,
        ideal_share=1.0,
        workers=args.workers,
        device=args.device,
        synthesis=synthesis,
        precision=precision,
        threads=args.threads,
        log_every=2,
        val_every=10**9,
        val_per_class=1,
        progress=False,
        warmup_steps=1,
    )
    train(cfg)
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    rates = [r["steps_per_s"] for r in records if r["kind"] == "train"][1:]
    return statistics.median(rates) * args.batch_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", action="append", default=[], help="none: procedural only")
    parser.add_argument("--member", default="small")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--patch", type=int, default=48)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--synthesis-batches", type=int, default=4)
    parser.add_argument("--precisions", default="fp32,bf16", help="comma-separated")
    parser.add_argument("--json", type=Path, default=Path("docs/synthesis_speed.json"))
    args = parser.parse_args()
    warnings.simplefilter("ignore", UserWarning)  # the index's held-out counts
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    result = {
        "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "cpu": f"{os.cpu_count()} cores, {cpu_words()}",
        "torch": torch.__version__,
        "member": args.member,
        "batch_size": args.batch_size,
        "patch": args.patch,
        "threads": args.threads,
        "workers": args.workers,
        "synthesis_alone": synthesis_rates(args, device),
    }
    with tempfile.TemporaryDirectory() as scratch:
        result["training_samples_per_s"] = {
            precision: {
                synthesis: training_rate(
                    args, synthesis, precision, Path(scratch, f"{precision}-{synthesis}")
                )
                for synthesis in ("numpy", "torch")
            }
            for precision in args.precisions.split(",")
        }
    print(json.dumps(result, indent=1))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
