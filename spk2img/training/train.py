"""Training Spk2ImgNet on simulated streams: hierarchical L1, Adam, checkpoints with resume,
JSONL metrics, periodic validation against TFP and TFI, and data parallelism under ``torchrun``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from spk2img.core.evaluation import baseline_scores, network_scorer, score, validation_set
from spk2img.core.provenance import git_commit
from spk2img.model.checkpoint import config_to_dict, load_checkpoint, save_checkpoint
from spk2img.model.config import get_config
from spk2img.model.network import Spk2ImgNet

from .data import SimulatedBatches
from .loss import hierarchical_l1


@dataclass
class TrainConfig:
    """One training run; every field is a ``spk2img train`` flag of the same name."""

    member: str = "tiny"
    """Family member to train (``spk2img models`` lists them)."""
    run_dir: str = "runs/default"
    """Where ``last.pt``, ``best.pt``, ``metrics.jsonl`` go; an existing ``last.pt`` is resumed."""
    steps: int = 20_000
    """Optimiser steps in all (a resumed run continues up to this)."""
    batch_size: int = 8
    """Windows per step and per process."""
    patch: int = 64
    """Side of the square training patches (a multiple of 4)."""
    lr: float = 5e-4
    """Peak Adam learning rate (after a linear warm-up); decays by a cosine to 2 % of it."""
    warmup_steps: int = 200
    seed: int = 0
    """Seed of the initial weights and of every batch (batches are a function of seed and step)."""
    cache_size: int = 0
    """Simulate this many samples once and train on them (0: a fresh sample every time)."""
    val_every: int = 500
    """Steps between validations (PSNR/SSIM on the fixed simulated validation set)."""
    val_per_class: int = 2
    """Validation scenes per (motion, brightness) class; 9 classes."""
    checkpoint_every: int = 100
    """Steps between checkpoints (``last.pt``)."""
    threads: int = 1
    """Torch intra-op threads per process."""
    log_every: int = 10
    """Steps between metrics lines."""
    progress: bool = True
    """Show a progress bar on stderr."""


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Learning rate at ``step``: linear warm-up, then a cosine from ``lr`` to ``0.02 * lr``."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    progress = min(1.0, (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps))
    return cfg.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress)))


class _Run:
    """Process-group membership: rank 0 logs, validates and writes checkpoints."""

    def __init__(self):
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        if self.world > 1 and not dist.is_initialized():
            dist.init_process_group("gloo")
        self.rank = dist.get_rank() if self.world > 1 else 0
        self.main = self.rank == 0

    def close(self):
        if self.world > 1:
            dist.destroy_process_group()


def train(cfg: TrainConfig) -> dict:
    """Run (or resume) training; returns the last validation scores (rank 0) or ``{}``."""
    run = _Run()
    torch.set_num_threads(cfg.threads)
    run_dir = Path(cfg.run_dir)
    torch.manual_seed(cfg.seed)
    model = Spk2ImgNet(get_config(cfg.member))
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    start, wall = 0, 0.0
    last = run_dir / "last.pt"
    if last.is_file():
        state = load_checkpoint(last)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start, wall = int(state["step"]), float(state["wall_s"])
    commit = state.get("commit", "unknown") if start else git_commit()  # the code that trains
    net = DistributedDataParallel(model) if run.world > 1 else model
    data = SimulatedBatches(
        cfg.patch, cfg.batch_size, cfg.seed, run.rank, cfg.cache_size, run_dir / "cache"
    )
    log = _Log(run_dir / "metrics.jsonl") if run.main else None
    scenes = validation_set(cfg.val_per_class) if run.main else []
    best = -math.inf
    if run.main and start == 0:
        log.write(kind="baselines", **baseline_scores(scenes))
    if run.main and (run_dir / "best.pt").is_file():
        best = float(load_checkpoint(run_dir / "best.pt").get("val_psnr", -math.inf))

    def checkpoint(path: Path, step: int, **extra) -> None:
        save_checkpoint(
            path,
            model=model.state_dict(),
            optimizer=optimizer.state_dict(),
            step=step,
            wall_s=wall,
            member=cfg.member,
            config=config_to_dict(model.config),
            train_config=dataclasses.asdict(cfg),
            commit=commit,
            **extra,
        )

    net.train()
    bar = tqdm(
        total=cfg.steps,
        initial=start,
        disable=not (run.main and cfg.progress),
        file=sys.stderr,
        unit="step",
    )
    val: dict = {}
    tick, tick_step = time.perf_counter(), start
    for step in range(start, cfg.steps):
        t0 = time.perf_counter()
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(cfg, step)
        spikes, truth = data.batch(step)
        image, estimates = net(spikes)
        loss = hierarchical_l1(image, estimates, truth)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        wall += time.perf_counter() - t0
        done = step + 1
        if not run.main:
            continue
        bar.update(1)
        if done % cfg.log_every == 0 or done == cfg.steps:
            rate = (done - tick_step) / (time.perf_counter() - tick)
            tick, tick_step = time.perf_counter(), done
            bar.set_postfix(loss=f"{loss.item():.4f}", steps_per_s=f"{rate:.2f}")
            log.write(
                kind="train",
                step=done,
                loss=loss.item(),
                lr=learning_rate(cfg, step),
                steps_per_s=rate,
                wall_s=wall,
            )
        if done % cfg.val_every == 0 or done == cfg.steps:
            val = validate(model, scenes)
            log.write(kind="val", step=done, wall_s=wall, **val)
            if val["psnr"] > best:
                best = val["psnr"]
                checkpoint(run_dir / "best.pt", done, val_psnr=best)
            model.train()
        if done % cfg.checkpoint_every == 0 or done == cfg.steps:
            checkpoint(last, done)
    bar.close()
    if run.world > 1:
        diff = replica_difference(model)
        if run.main:
            log.write(kind="replicas", world_size=run.world, max_abs_diff=diff)
    run.close()
    return val


def validate(model: Spk2ImgNet, scenes) -> dict:
    """Validation PSNR/SSIM of ``model`` (switched to eval mode) on ``scenes``."""
    model.eval()
    with torch.inference_mode():

        def predict(windows: np.ndarray) -> np.ndarray:
            return model(torch.from_numpy(windows))[0][:, 0].numpy()

        return score(network_scorer(predict), scenes)


def replica_difference(model: torch.nn.Module) -> float:
    """Largest absolute difference of any weight between the data-parallel replicas."""
    flat = torch.cat([p.detach().reshape(-1) for p in model.parameters()])
    copies = [torch.empty_like(flat) for _ in range(dist.get_world_size())]
    dist.all_gather(copies, flat)
    return max(float((c - copies[0]).abs().max()) for c in copies)


class _Log:
    """Append-only JSONL metrics log, one object per line, flushed at once."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path

    def write(self, **record) -> None:
        record["time"] = time.time()
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
