"""Training batches: 41-frame windows and ground truth at the five block centres, from
procedural scenes, natural photographs and real clips mixed at set weights (photos and clips
made light by either convention of :mod:`spk2img.sim.sources`), filmed by an ideal or a
real-like sensor, with random 90° rotations and flips.

Every sample is a pure function of ``(seed, rank, step, index in batch)``, so a resumed run sees
exactly the batches it would have seen, each data-parallel rank sees different ones, and worker
processes may make them in any order.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import time
import warnings
from collections import deque
from dataclasses import dataclass

import numpy as np

from spk2img.model.config import PUBLISHED_GEOMETRY, Geometry
from spk2img.sim.natural_scenes import MAX_LAYERS, clip_scene, photo_scene
from spk2img.sim.scenes import (
    BRIGHTNESSES,
    MOTIONS,
    PROCEDURAL_KINDS,
    TRAINING_MOTIONS,
    Scene,
    random_scene,
)
from spk2img.sim.simulator import SensorConfig, ground_truth, simulate
from spk2img.sim.sources import SourceIndex, load_clip, load_photo

from .config import check_share

KINDS = ("procedural", "photos", "clips")


@dataclass(frozen=True)
class DataMix:
    """Shares of the three kinds of training content (they need not sum to 1)."""

    procedural: float = 1.0
    photos: float = 0.0
    clips: float = 0.0

    @classmethod
    def parse(cls, text: str) -> DataMix:
        """``"photos=0.5,clips=0.3,procedural=0.2"`` -> a mix (missing kinds weigh 0)."""
        return cls(**parse_shares(text, KINDS, "data mix", "kinds"))

    def weights(self) -> np.ndarray:
        w = np.array([self.procedural, self.photos, self.clips], np.float64)
        return w / w.sum()


def parse_shares(text: str, names: tuple[str, ...], what: str, noun: str) -> dict[str, float]:
    """``"a=0.5,b=0.3"`` -> a weight for each of ``names`` (missing ones weigh 0); a
    ``ValueError`` saying ``bad {what} {text!r}: ...`` for anything else (``noun`` names what
    ``names`` are), and for weights that are negative, not finite or all 0."""
    try:
        pairs = [item.split("=") for item in text.split(",") if item.strip()]
        weights = {name.strip(): float(value) for name, value in pairs}
    except ValueError:
        example = ",".join(f"{name}=0.5" for name in names[:2])
        raise ValueError(f"bad {what} {text!r}: use e.g. {example}") from None
    unknown = set(weights) - set(names)
    values = list(weights.values())
    if unknown or not all(0 <= v < math.inf for v in values) or sum(values) <= 0:
        raise ValueError(
            f"bad {what} {text!r}: {noun} are {', '.join(names)}, weights >= 0, not all 0"
        )
    return {name: weights.get(name, 0.0) for name in names}


def speed_weights(text: str) -> dict[str, float] | None:
    """``"static=0,slow=0.7,moderate=0.2,fast=0.1"`` -> motion class -> probability, over
    :data:`~spk2img.sim.scenes.MOTIONS` in their order, then ``moderate`` where its share is not
    0; None for ``""`` or equal shares of the three (drawn as before the mix existed, so such
    runs keep their batches, as runs without ``moderate`` keep theirs)."""
    if not text:
        return None
    shares = parse_shares(text, TRAINING_MOTIONS, "speed mix", "classes")
    names = [name for name in TRAINING_MOTIONS if name in MOTIONS or shares[name] > 0]
    weights = np.array([shares[name] for name in names])
    if len(names) == len(MOTIONS) and np.all(weights == weights[0]):
        return None
    return dict(zip(names, weights / weights.sum(), strict=True))


def draw_augmentation(rng: np.random.Generator) -> tuple[int, bool]:
    """A random rotation by ``k`` quarter turns (0-3) and whether to mirror after it."""
    return int(rng.integers(4)), bool(rng.integers(2))


def augment(array: np.ndarray, quarter_turns: int, mirror: bool) -> np.ndarray:
    """``(c, h, w)`` ``array`` rotated by ``quarter_turns`` · 90° (from ``h`` towards ``w``),
    then mirrored left-right if ``mirror``."""
    array = np.rot90(array, quarter_turns, axes=(1, 2))
    return array[:, :, ::-1] if mirror else array


@dataclass(frozen=True)
class ScenePlan:
    """A training sample before filming (torch synthesis films it on the training device)."""

    scene: Scene
    sensor: SensorConfig
    quarter_turns: int
    mirror: bool


class SampleMaker:
    """Makes training samples (module doc); picklable, so worker processes hold a copy.

    Args:
        patch: side of the square patches (a multiple of the network's size multiple).
        seed, rank: the run's seed and this process's data-parallel rank.
        mix: shares of procedural, photo and clip content.
        index: the natural content (None: procedural only, whatever ``mix`` says).
        real_sensor: the real-like regime, drawn around it per sample (the samples that are
            not ideal); None: :meth:`SensorConfig.random`'s draws for every sample.
        ideal_share: share of the samples filmed by the ideal sensor when ``real_sensor`` is
            given (0.5: half and half; 1: noise-free data only, like simulated datasets).
        geometry: the trained network's window and blocks (the frames filmed, and the block
            centres the ground truth is taken at).
        display_share: share of the photo and clip samples read by the ``display`` light
            convention (value / 255 is the light), the others by ``linear``.
        speeds: motion class -> probability (:func:`speed_weights`); None: static, slow and
            fast a third each.
    """

    def __init__(
        self,
        patch: int,
        seed: int,
        rank: int = 0,
        mix: DataMix | None = None,
        index: SourceIndex | None = None,
        real_sensor: SensorConfig | None = None,
        ideal_share: float = 0.5,
        geometry: Geometry = PUBLISHED_GEOMETRY,
        display_share: float = 0.0,
        speeds: dict[str, float] | None = None,
    ):
        check_share("ideal_share", ideal_share)
        check_share("display_share", display_share)
        self.display_share, self.speeds = display_share, speeds
        self.geometry = geometry
        self.patch, self.seed, self.rank = patch, seed, rank
        self.index, self.real_sensor, self.ideal_share = index, real_sensor, ideal_share
        mix = mix or DataMix()
        has_photos, has_clips = bool(index and index.photos), bool(index and index.clips)
        photos, clips = mix.photos * has_photos, mix.clips * has_clips
        self.weights = DataMix(mix.procedural if photos + clips else 1.0, photos, clips).weights()

    def sample(self, step: int, item: int) -> tuple[np.ndarray, np.ndarray]:
        """Item ``item`` of the batch of ``step``: ``(F, P, P) uint8`` spikes (the geometry's
        window, 41 as published) and ``(blocks, P, P) float32`` ground truth at the block
        centres, augmented; filmed by the numpy simulator."""
        rng, scene, sensor = self.draw(step, item)
        spikes = simulate(scene, self.geometry.window_frames, sensor, rng)
        truth = ground_truth(scene, self.geometry.block_centres)
        quarter_turns, mirror = draw_augmentation(rng)
        return augment(spikes, quarter_turns, mirror), augment(truth, quarter_turns, mirror)

    def plan(self, step: int, item: int) -> ScenePlan:
        """Item ``item`` of the batch of ``step`` before filming: its scene, sensor and
        augmentation (the same scene and sensor as :meth:`sample`'s)."""
        _, scene, sensor = self.draw(step, item)
        rng = np.random.default_rng([self.seed, self.rank, step, item, 1])
        return ScenePlan(scene, sensor, *draw_augmentation(rng))

    def draw(self, step: int, item: int) -> tuple[np.random.Generator, Scene, SensorConfig]:
        """The scene and sensor of item ``item`` of the batch of ``step``, and the generator
        they were drawn from (the numpy simulator goes on drawing from it)."""
        rng = np.random.default_rng([self.seed, self.rank, step, item])
        kind = KINDS[int(rng.choice(len(KINDS), p=self.weights))]
        if self.speeds is None:
            motion = str(rng.choice(MOTIONS))
        else:
            motion = str(rng.choice(list(self.speeds), p=np.array(list(self.speeds.values()))))
        brightness = str(rng.choice(BRIGHTNESSES))
        p = self.patch
        try:
            if kind != "procedural":
                light = self.draw_light(rng)
            if kind == "photos":
                picks = rng.integers(len(self.index.photos), size=1 + MAX_LAYERS)
                photos = [load_photo(self.index.photos[k].path, light) for k in picks]
                scene = photo_scene(rng, photos, p, p, motion, brightness)
                scene.meta["light"] = light
            elif kind == "clips":
                clip = self.index.clips[int(rng.integers(len(self.index.clips)))]
                scene = clip_scene(rng, load_clip(clip), p, p, motion, brightness, light)
        except (OSError, ValueError) as exc:  # a file that broke after the index was built
            warnings.warn(f"training data: {exc}; a procedural sample instead", stacklevel=2)
            kind = "procedural"
        if kind == "procedural":
            scene = random_scene(rng, p, p, motion, brightness, PROCEDURAL_KINDS)
        return rng, scene, self.draw_sensor(rng)

    def draw_light(self, rng: np.random.Generator) -> str:
        """``display`` with probability ``display_share``, else ``linear`` (drawn from ``rng``
        only for a share strictly between 0 and 1, so single-convention runs keep their
        batches)."""
        if 0 < self.display_share < 1:
            return "display" if rng.uniform() < self.display_share else "linear"
        return "display" if self.display_share == 1 else "linear"

    def draw_sensor(self, rng: np.random.Generator) -> SensorConfig:
        """Ideal with probability ``ideal_share``, else the real-like regime (module doc)."""
        if self.real_sensor is None:
            return SensorConfig.random(rng)
        if rng.uniform() < self.ideal_share:
            return SensorConfig.ideal()
        return self.real_sensor.jittered(rng)

    def batch(self, step: int, size: int) -> tuple[np.ndarray, np.ndarray]:
        """``(size, F, P, P) float32`` spikes and ``(size, blocks, P, P) float32`` truth."""
        pairs = [self.sample(step, item) for item in range(size)]
        spikes = np.stack([np.ascontiguousarray(s, np.float32) for s, _ in pairs])
        truth = np.stack([np.ascontiguousarray(t, np.float32) for _, t in pairs])
        return spikes, truth

    def plans(self, step: int, size: int) -> list[ScenePlan]:
        """The :meth:`plan` of every item of the batch of ``step``."""
        return [self.plan(step, item) for item in range(size)]


_WORKER_MAKER: SampleMaker | None = None


def _init_worker(maker: SampleMaker) -> None:
    global _WORKER_MAKER
    _WORKER_MAKER = maker
    # Ctrl-C, `timeout` and schedulers signal every process of the command's group: the
    # training process decides when to stop (spk2img.training.stop). A worker killed by such a
    # signal could hold the pool's queue lock and never return its batch, and the pool's
    # replacement worker would wait on that lock for ever: so the workers leave the group
    # (the pool still ends them by pid) and ignore Ctrl-C before they do
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.setpgrp()


def _worker_batch(make: str, step: int, size: int):
    return getattr(_WORKER_MAKER, make)(step, size)


CLOSE_WAIT_S = 30.0
"""Seconds :meth:`Batches.close` waits for the batches in flight before terminating workers."""


class Batches:
    """``next()`` -> the batches of ``start``, ``start + 1``, ... in order, made ahead by
    ``workers`` processes (0: in this process), at most ``2 * workers`` batches ahead: the
    maker's filmed arrays (``make="batch"``) or its scene plans (``make="plans"``)."""

    def __init__(
        self,
        maker: SampleMaker,
        batch_size: int,
        start: int,
        workers: int = 0,
        make: str = "batch",
    ):
        if make not in ("batch", "plans"):
            raise ValueError(f"make={make!r}: batch or plans")
        self.maker, self.batch_size, self.step, self.make = maker, batch_size, start, make
        self.pool = None
        self.pending: deque = deque()
        if workers > 0:
            context = multiprocessing.get_context("spawn")
            self.pool = context.Pool(workers, initializer=_init_worker, initargs=(maker,))
            self.depth = 2 * workers
            for _ in range(self.depth):
                self._submit()

    def _submit(self) -> None:
        step = self.step + len(self.pending)  # pending holds the batches of self.step on
        args = (self.make, step, self.batch_size)
        self.pending.append(self.pool.apply_async(_worker_batch, args))

    def next(self) -> tuple[np.ndarray, np.ndarray]:
        if self.pool is None:
            out = getattr(self.maker, self.make)(self.step, self.batch_size)
            self.step += 1
            return out
        out = self.pending.popleft().get()
        self.step += 1
        self._submit()
        return out

    def close(self) -> None:
        """Stop the workers. The batches in flight finish first (up to :data:`CLOSE_WAIT_S`)
        and the pool closes; only workers still busy after that are terminated. (Terminating a
        worker while it writes a batch back leaves the result queue's lock held, and the
        pool's own threads then wait on it forever.)"""
        if self.pool is None:
            return
        deadline = time.monotonic() + CLOSE_WAIT_S
        for result in self.pending:
            result.wait(max(0.0, deadline - time.monotonic()))
        if all(result.ready() for result in self.pending):
            self.pool.close()
        else:
            self.pool.terminate()
        self.pool.join()
        self.pool = None
        self.pending.clear()
