"""Training Spk2ImgNet on simulated streams: hierarchical L1 (or PSNR), Adam, checkpoints with
resume, JSONL metrics, periodic validation against TFP and TFI, and data parallelism under
``torchrun``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from contextlib import closing, nullcontext
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from spk2img.errors import InputError
from spk2img.evaluation.alignment_probe import alignment_slopes
from spk2img.evaluation.natural_validation import NEVER_TRAINED, natural_validation_set
from spk2img.evaluation.real_video import load_windows, real_video_scores, training_windows
from spk2img.evaluation.scoring import baseline_scores, network_scorer, score, validation_set
from spk2img.hardware import cpu_words
from spk2img.model.checkpoint import (
    config_to_dict,
    load_checkpoint,
    load_weights,
    save_checkpoint,
    stored_config,
)
from spk2img.model.config import MOTION_SETTINGS, get_config, with_motion
from spk2img.model.growth import grow_weights
from spk2img.model.network import Spk2ImgNet
from spk2img.provenance import git_commit
from spk2img.sim.sensor_fit import FITTED_PRESET, load_preset
from spk2img.sim.sources import SourceIndex

from .alignment_loss import alignment_term, recorded_shifts
from .config import TrainConfig
from .data import Batches, DataMix, SampleMaker, speed_weights
from .ema import WeightAverage
from .loss import hierarchical_loss
from .stop import StopRequest
from .synthesis import batch_generator, film_plans

CHECKPOINT_SECONDS = 600.0


def selection_set(ideal_share: float, natural: bool, real_video: bool = False) -> str:
    """What ``best.pt`` is chosen on: for a noise-free run (ideal share 1) the real-video
    validation when its clips are in the data (``real video``: the set that predicts scores on
    real video); else the natural validation in the sensor regime the run films (``natural
    ideal`` for an ideal share of 1, ``natural fitted`` for 0, ``natural``, both, in between);
    ``procedural`` without natural data."""
    if real_video and ideal_share == 1:
        return "real video"
    if not natural:
        return "procedural"
    regime = {1: "ideal", 0: "fitted"}.get(ideal_share)
    return f"natural {regime}" if regime else "natural"


def selection_score(val: dict, selection: str) -> float:
    """The PSNR (dB) of a validation record ``val`` that :func:`selection_set` names."""
    if selection == "procedural":
        return val["psnr"]
    if selection == "real video":
        return val["real_video"]["psnr"]
    regime = selection.removeprefix("natural").strip()
    return val["natural"][f"psnr_{regime}" if regime else "psnr"]


def logged_best(path: Path, selection: str, until: int) -> float:
    """The best score on ``selection`` (dB) among the validations that the metrics log ``path``
    records up to step ``until``; ``-inf`` for none. A resumed run writes ``best.pt`` only for a
    checkpoint that beats every validation before it, whether or not that one's ``best.pt`` was
    kept."""
    scores = [-math.inf]
    if path.is_file():
        for line in path.read_text().splitlines():
            record = json.loads(line)
            if record.get("kind") == "val" and record["step"] <= until:
                try:
                    scores.append(selection_score(record, selection))
                except KeyError:  # validated on other sets then
                    pass
    return max(scores)


SELECTIONS = (
    "procedural",
    "real video",
    "real video frames",
    "natural",
    "natural ideal",
    "natural fitted",
)
"""Every score a checkpoint's ``val_set`` may name: :func:`selection_set`'s, and ``real video
frames`` (the whole-frame real-video validation, scored after a run: a weight mean's)."""


def selection_words(selection: str) -> str:
    """The score :func:`selection_set` names, in words (for the model card)."""
    if selection == "procedural":
        return "the procedural validation's PSNR"
    if selection == "real video":
        return "the real-video validation's PSNR (crops of the held-out real clips)"
    if selection == "real video frames":  # a candidate scored after the run (--chosen-on)
        return "the real-video validation's PSNR on whole frames (docs/real_video.md)"
    regime = selection.removeprefix("natural").strip()
    return f"its {regime}-regime PSNR" if regime else "the mean PSNR of both regimes"


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
        """Leave the group together: every rank waits at a barrier before the group goes, so
        none tears gloo down while another still has work on it (a rank that did aborted at
        exit, SIGABRT, after a finished run)."""
        if self.world > 1:
            dist.barrier()
            dist.destroy_process_group()


def train(cfg: TrainConfig) -> dict:
    """Run (or resume) training; returns (and logs, as the ``summary`` record) where the run and
    its best checkpoint are, what the best was chosen on and scored, the wall time of optimiser
    steps and the last validation's scores (empty on ranks other than 0, which do not
    validate). A run stopped by a signal (:mod:`spk2img.training.stop`) saves ``last.pt`` at
    the step it reached and returns, logging a ``stopped`` record instead of the summary;
    ``stopped`` then holds the signal's name and the step (None for a run that reached
    ``cfg.steps``)."""
    device = training_device(cfg.device)
    run = _Run()
    torch.set_num_threads(cfg.threads)
    run_dir = Path(cfg.run_dir)
    torch.manual_seed(cfg.seed)
    model = Spk2ImgNet(with_motion(get_config(cfg.member), cfg.motion))
    if cfg.patch % model.config.size_multiple:
        raise InputError(
            f"--patch {cfg.patch}: must be a multiple of {model.config.size_multiple} for "
            f"{cfg.member}"
        )
    bf16 = cfg.autocasts_bf16()
    memory_format = training_memory_format(device, bf16)
    model.to(device, memory_format=memory_format)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    start, wall = 0, 0.0
    last = run_dir / "last.pt"
    if last.is_file():
        state = load_checkpoint(last)
        stored = stored_config(state, last)
        if stored != model.config and shape_of(stored) == shape_of(model.config):
            raise InputError(
                f"{last} was trained with other motion settings ({motion_of(stored)}): continue "
                "it with the --motion it was started with"
            )
        if stored != model.config:
            raise InputError(
                f"{last} holds another shape than --member {cfg.member} has now: continue it "
                "with the code that started it, or train in a new --run-dir"
            )
        if "optimizer" not in state:
            raise InputError(
                f"{last} holds weights only, no optimiser state to resume: start a new run "
                f"from it with --init {last} (and another --run-dir)"
            )
        load_weights(model, state, last)
        optimizer.load_state_dict(state["optimizer"])
        start, wall = int(state["step"]), float(state["wall_s"])
        init_from = state.get("init_from")
    elif cfg.init:
        init_from = load_initial_weights(model, cfg.init)
    else:
        init_from = None
    average = WeightAverage(model, cfg.ema_decay) if cfg.ema_decay else None
    if average and start and "ema" in state:  # a run that averaged before: its average goes on
        average.model.load_state_dict(state["ema"])
    scored = average.model if average else model  # what validation scores and best.pt keeps
    commit = state.get("commit", "unknown") if start else git_commit()  # the code that trains
    origin = {  # what trains and from what: in every checkpoint and each (re)start's log record
        "member": cfg.member,
        "train_config": dataclasses.asdict(cfg),
        "hardware": describe_hardware(device, cfg.threads, bf16),
        "commit": commit,
        "init_from": init_from,
    }
    net = DistributedDataParallel(model) if run.world > 1 else model
    index = SourceIndex.scan(cfg.data, cfg.patch, NEVER_TRAINED) if cfg.data else None
    real_sensor = load_preset(cfg.sensor_preset or FITTED_PRESET)
    mix = DataMix.parse(cfg.data_mix)
    maker = SampleMaker(
        cfg.patch,
        cfg.seed,
        run.rank,
        mix,
        index,
        real_sensor,
        cfg.ideal_share,
        model.config.geometry,
        cfg.display_share,
        speed_weights(cfg.speed_mix),
    )
    films_on_device = cfg.films_on_device()
    make = "plans" if films_on_device else "batch"
    log = _Log(run_dir / "metrics.jsonl") if run.main else None
    val_sets = {}
    if run.main:
        log.write(kind="run", step=start, **origin)
        val_sets["natural"] = natural_validation_set(cfg.data) if cfg.data else []
        val_sets["procedural"] = validation_set(cfg.val_per_class)
        val_sets["real_video"] = real_video_windows(cfg)
        log.write(
            kind="data",
            step=start,
            sources=index.summary() if index else None,
            mix=dict(zip(("procedural", "photos", "clips"), maker.weights.tolist(), strict=True)),
            real_sensor=dataclasses.asdict(real_sensor),
            ideal_share=cfg.ideal_share,
            display_share=cfg.display_share if index else None,
            synthesis="torch" if films_on_device else "numpy",
            natural_validation_scenes=len(val_sets["natural"]),
            real_video_windows=len(val_sets["real_video"]),
        )
    selection = selection_set(
        cfg.ideal_share, bool(val_sets.get("natural")), bool(val_sets.get("real_video"))
    )
    best = -math.inf
    if run.main and start == 0:
        log.write(kind="baselines", **baseline_scores(val_sets["procedural"]))
        if val_sets["natural"]:
            log.write(kind="natural_baselines", **baseline_scores(val_sets["natural"]))
    if run.main and (run_dir / "best.pt").is_file():
        previous = load_checkpoint(run_dir / "best.pt")
        if previous.get("val_set", "procedural") == selection:
            best = float(previous.get("val_psnr", -math.inf))
    if run.main and start:  # best.pt may be gone (the repository keeps last.pt alone)
        best = max(best, logged_best(run_dir / "metrics.jsonl", selection, start))

    def checkpoint(path: Path, step: int, network: torch.nn.Module, **extra) -> None:
        save_checkpoint(
            path,
            model=network.state_dict(),
            weights="trained" if network is model else "average",
            optimizer=optimizer.state_dict(),
            step=step,
            wall_s=wall,
            config=config_to_dict(model.config),
            **origin,
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
    saved_at = time.monotonic()
    stopping = False
    with (
        StopRequest() as stop,
        closing(Batches(maker, cfg.batch_size, start, cfg.workers, make)) as batches,
    ):
        for step in range(start, cfg.steps):
            t0 = time.perf_counter()
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(cfg, step)
            if films_on_device:
                generator = batch_generator(cfg.seed, run.rank, step, device)
                batch = film_plans(batches.next(), model.config.geometry, generator)
            else:
                batch = (torch.from_numpy(a).to(device) for a in batches.next())
            spikes, truth = (a.contiguous(memory_format=memory_format) for a in batch)
            with (
                torch.autocast(device.type, torch.bfloat16, enabled=bf16),
                recorded_shifts(model) if cfg.align_weight else nullcontext({}) as shifts,
            ):
                image, estimates = net(spikes)
                loss = hierarchical_loss(image.float(), estimates.float(), truth, cfg.loss)
            if cfg.align_weight:
                align = alignment_term(shifts, truth, model.config.feature_stride)
                loss = loss + cfg.align_weight * align
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            if average:
                average.update(model)
            wall += time.perf_counter() - t0
            done = step + 1
            stopping = stop.agreed(run.world) and done < cfg.steps
            if not run.main:
                if stopping:
                    break
                continue
            bar.update(1)
            if done % cfg.log_every == 0 or done == cfg.steps:
                rate = (done - tick_step) / (time.perf_counter() - tick)
                tick, tick_step = time.perf_counter(), done
                eta = (cfg.steps - done) / rate
                speed = f"{rate:.2f}"
                bar.set_postfix(loss=f"{loss.item():.4f}", steps_per_s=speed, eta=f"{eta:.0f}s")
                log.write(
                    kind="train",
                    step=done,
                    loss=loss.item(),
                    **({"align": align.item()} if cfg.align_weight else {}),
                    lr=learning_rate(cfg, step),
                    steps_per_s=rate,
                    eta_s=eta,
                    wall_s=wall,
                )
            if (done % cfg.val_every == 0 and not stopping) or done == cfg.steps:
                val = validate(scored, val_sets["procedural"])
                if val_sets["natural"]:
                    val["natural"] = validate(scored, val_sets["natural"])
                if val_sets["real_video"]:
                    val["real_video"] = validate_real_video(scored, val_sets["real_video"])
                    val["alignment_slopes"] = probe_alignment(scored, val_sets["real_video"])
                    if average:  # the weights as trained, beside their average
                        val["real_video_trained"] = validate_real_video(
                            model, val_sets["real_video"]
                        )
                log.write(kind="val", step=done, wall_s=wall, **val)
                chosen = selection_score(val, selection)
                if chosen > best:
                    best = chosen
                    checkpoint(run_dir / "best.pt", done, scored, val_psnr=best, val_set=selection)
                model.train()
            periodic = time.monotonic() - saved_at >= CHECKPOINT_SECONDS
            if done % cfg.checkpoint_every == 0 or done == cfg.steps or periodic or stopping:
                checkpoint(
                    last, done, model, **({"ema": average.model.state_dict()} if average else {})
                )
                saved_at = time.monotonic()
            if stopping:
                log.write(kind="stopped", step=done, wall_s=wall, signal=stop.name)
                break
    bar.close()
    if run.world > 1:
        diff = replica_difference(model)
        if run.main:
            log.write(kind="replicas", world_size=run.world, max_abs_diff=diff)
    run.close()
    summary = {
        "run_dir": str(run_dir),
        "steps": cfg.steps,
        "wall_s": wall,
        "best_checkpoint": str(run_dir / "best.pt") if (run_dir / "best.pt").is_file() else None,
        "val_set": selection,
        "best_psnr": best,
        "last_validation": val,
        "stopped": {"signal": stop.name, "step": done} if stopping else None,
    }
    if run.main and not stopping:
        log.write(kind="summary", **summary)
    return summary


def motion_of(config) -> dict:
    """``config``'s weight-free motion fields (:data:`~spk2img.model.config.MOTION_SETTINGS`)."""
    return {name: getattr(config, name) for name in MOTION_SETTINGS.values()}


def shape_of(config) -> dict:
    """``config``'s fields other than its motion's (:func:`motion_of`), as a dict."""
    motion = MOTION_SETTINGS.values()
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in motion}


def load_initial_weights(model: Spk2ImgNet, path: str) -> dict:
    """Load the weights of checkpoint ``path`` into ``model`` (the same shape, or one the
    checkpoint's network grows into: :mod:`spk2img.model.growth`) and return where they came
    from: the path, the run that wrote it (its run folder's name, where the checkpoint records
    one), and the step, wall time, member and commit that trained them."""
    state = load_checkpoint(path)
    stored = stored_config(state, path)
    if stored == model.config:
        load_weights(model, state, path)
    else:  # another shape: grown (it starts computing what the checkpoint's did) or refused
        try:
            grow_weights(model, state["model"], stored)
        except ValueError as exc:
            raise InputError(
                f"--init {path}: another shape than the member being trained, which it cannot "
                f"grow into: {exc}"
            ) from exc
    run_dir = state.get("train_config", {}).get("run_dir")
    return {
        "path": str(path),
        "run": Path(run_dir).name if run_dir else None,
        "member": state.get("member"),
        "step": int(state.get("step", 0)),
        "wall_s": float(state.get("wall_s", 0.0)),
        "commit": state.get("commit", "unknown"),
    }


def describe_hardware(device: torch.device, threads: int, bf16: bool) -> str:
    """What trains and how: the GPU's name, or the CPU's cores, model (and bf16 matrix units)
    and the threads used, and the arithmetic where it is bf16 autocast."""
    arithmetic = ", bf16 autocast" if bf16 else ""
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (CUDA{arithmetic})"
    return f"a {os.cpu_count()}-core {cpu_words()} CPU, {threads} torch thread(s){arithmetic}"


def training_memory_format(device: torch.device, bf16: bool) -> torch.memory_format:
    """The memory order of weights and batches: channels-last on CUDA (what the GPU runs used;
    cuDNN's bf16 convolutions want it) and for bf16 on the CPU (oneDNN's bf16 convolutions:
    alternated steps of batch 8 at 64x64, one thread of an Intel Xeon with AMX, torch 2.13:
    `small` 6.0 s against 7.0, `cpu` 0.91 against 1.04, medians), the default order for fp32 on
    the CPU, where a step of every member took less time in it on an AMD EPYC (`small` 15.7 s
    against 18.7, `cpu` 1.68 against 1.99, `tiny` 6.0 against 6.6, `lite` 3.45 against 3.62)."""
    return torch.channels_last if device.type == "cuda" or bf16 else torch.contiguous_format


def real_video_windows(cfg: TrainConfig) -> list:
    """The real-video validation's windows: read from ``--real-video-windows``, else filmed
    from the clips under ``--data`` (none without either)."""
    if cfg.real_video_windows:
        try:
            return load_windows(cfg.real_video_windows)
        except ValueError as exc:
            raise InputError(f"--real-video-windows {exc}") from exc
    return training_windows(cfg.data) if cfg.data else []


def training_device(name: str) -> torch.device:
    """``cpu`` or ``cuda`` as a device; CUDA asked for where there is none is an input error."""
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device {name}: choose cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available (torch sees none)")
    return torch.device(name)


def validate(model: Spk2ImgNet, scenes) -> dict:
    """Validation PSNR/SSIM of ``model`` (switched to eval mode) on ``scenes``."""
    with torch.inference_mode():
        return score(_scorer(model), scenes)


def validate_real_video(model: Spk2ImgNet, windows: list) -> dict:
    """:func:`~spk2img.evaluation.real_video.real_video_scores` of ``model`` (switched to eval
    mode) on the real-video ``windows``."""
    with torch.inference_mode():
        net = _scorer(model)
        return real_video_scores(windows, [net(w.spikes, w.truth) for w in windows])


def probe_alignment(model: Spk2ImgNet, windows: list) -> dict[str, float]:
    """How far ``model``'s deformable convs follow a pan
    (:func:`~spk2img.evaluation.alignment_probe.alignment_slopes`: 1 follows, 0 ignores), on
    the first real-video window's truth (its borders mirrored)."""
    truth = windows[0].truth
    return alignment_slopes(model, truth, *truth.shape)


def _scorer(model: Spk2ImgNet):
    """``model`` in eval mode as a ``(spikes, truth) -> (H, W) image`` method (evaluation.scoring),
    reading the centred crop of its own window."""
    model.eval()
    device = next(model.parameters()).device

    def predict(windows: np.ndarray) -> np.ndarray:
        return model(torch.from_numpy(windows).to(device))[0][:, 0].float().cpu().numpy()

    return network_scorer(predict, model.config.geometry)


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
