"""Spike-camera simulator: integrate-and-fire (docs/format.md) with optional real-sensor noises.

Each pixel integrates charge ``∫ 0.6·I dt`` (time in frame intervals; ``I`` linear in [0, 1]),
sampled ``substeps`` times per frame interval (midpoint rule, so motion blurs inside a frame).
When the charge reaches the pixel's threshold a spike is flagged and the threshold subtracted
(the rest is kept); the flag is read at the end of each interval, so a pixel fires at most once
a frame. Charge only grows within a frame, so "crossed at some substep" equals "at or above the
threshold at the end of the interval". Overflow is kept, but the charge left after a frame is
clamped to one threshold: a pixel whose input exceeds one threshold per frame (hot pixels,
saturating noise) fires every frame instead of accumulating charge without bound. Below
saturation the clamp never acts. The initial charge is uniform in [0, threshold).

Ground-truth convention: the ground truth of frame ``k`` is ``scene.intensity(t0 + k + 0.5)``,
the intensity in the middle of frame ``k``'s interval ``[t0 + k, t0 + k + 1)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from spk2img.io.light import SPIKE_RATE
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.sim.scenes import Scene, random_scene

FILM_FRAMES = PUBLISHED_GEOMETRY.window_frames
"""Frames of every simulated window (training samples, validation, test and benchmark sets): the
published window, 41; a network with a shorter window reads their centred crop."""
CENTER_FRAME = PUBLISHED_GEOMETRY.half
"""The frame a simulated window is reconstructed at: its centre, 20."""
GT_FRAMES = PUBLISHED_GEOMETRY.block_centres
"""The block centres of the published window, 6, 13, 20, 27 and 34: where training's ground
truth is taken."""
RENDER_BUDGET = 2**20  # scene samples rendered at once (substeps x pixels x frames)


@dataclass(frozen=True)
class SensorConfig:
    """Sensor model; the defaults are the noise-free integrate-and-fire of spike-REDS."""

    threshold: float = 1.0
    """Nominal firing threshold in charge units; the light adds 0.6·I units a frame."""
    shot_noise: bool = False
    """Photon shot noise: a frame's charge is Poisson(photons) / photons_per_threshold."""
    photons_per_threshold: float = 50.0
    """Photons (and dark electrons) per nominal threshold, for the shot noise only."""
    dark_current: float = 0.0
    """Intensity-independent extra spikes per frame at every pixel."""
    threshold_mismatch: float = 0.0
    """Relative standard deviation of the per-pixel threshold (fixed pattern noise)."""
    hot_pixel_fraction: float = 0.0
    """Fraction of pixels that are hot."""
    hot_pixel_rate: float = 0.0
    """Extra spikes per frame of a hot pixel."""

    def __post_init__(self) -> None:
        if not (self.threshold > 0 and self.photons_per_threshold > 0):
            raise ValueError("threshold and photons_per_threshold must be > 0")
        if min(self.dark_current, self.threshold_mismatch, self.hot_pixel_rate) < 0:
            raise ValueError("dark_current, threshold_mismatch and hot_pixel_rate must be >= 0")
        if not 0 <= self.hot_pixel_fraction <= 1:
            raise ValueError("hot_pixel_fraction must be in [0, 1]")

    @classmethod
    def ideal(cls) -> SensorConfig:
        """Noise-free integrate-and-fire, as the public spike-REDS streams."""
        return cls()

    @classmethod
    def real(cls) -> SensorConfig:
        """All four noises of a real capture on, at typical strengths."""
        return cls(
            shot_noise=True,
            photons_per_threshold=50.0,
            dark_current=0.002,
            threshold_mismatch=0.03,
            hot_pixel_fraction=1e-4,
            hot_pixel_rate=0.5,
        )

    def jittered(self, rng: np.random.Generator) -> SensorConfig:
        """This sensor with each noise's strength scaled by a log-uniform factor in [1/2, 2],
        except the dark current, drawn uniformly in [0, 2 x] its value (a fitted preset holds
        the middle of what its capture allows, :mod:`spk2img.sim.sensor_fit`)."""

        def factor() -> float:
            return float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))

        return SensorConfig(
            threshold=self.threshold,
            shot_noise=self.shot_noise,
            photons_per_threshold=self.photons_per_threshold * factor(),
            dark_current=float(rng.uniform(0, 2 * self.dark_current)),
            threshold_mismatch=self.threshold_mismatch * factor(),
            hot_pixel_fraction=min(1.0, self.hot_pixel_fraction * factor()),
            hot_pixel_rate=self.hot_pixel_rate * factor(),
        )

    @classmethod
    def random(cls, rng: np.random.Generator) -> SensorConfig:
        """Half the time ideal, else a real-like sensor with each noise's strength drawn around
        :meth:`real` (photons 20-200 log-uniform, dark 0-0.005, mismatch 0-0.06, hot pixels
        0-3e-4 at 0.2-0.9 spikes/frame)."""
        if rng.uniform() < 0.5:
            return cls.ideal()
        return cls(
            shot_noise=True,
            photons_per_threshold=float(np.exp(rng.uniform(np.log(20), np.log(200)))),
            dark_current=float(rng.uniform(0, 0.005)),
            threshold_mismatch=float(rng.uniform(0, 0.06)),
            hot_pixel_fraction=float(rng.uniform(0, 3e-4)),
            hot_pixel_rate=float(rng.uniform(0.2, 0.9)),
        )


def substep_times(t0: float, n_frames: int, substeps: int) -> np.ndarray:
    """``(n_frames * substeps,) float64``: the midpoints of the ``substeps`` equal parts of
    each frame interval from ``t0`` on, frame by frame (where the simulator samples light)."""
    return (t0 + np.arange(n_frames)[:, None] + (np.arange(substeps) + 0.5) / substeps).ravel()


class SpikeSimulator:
    """A sensor filming ``scene`` from time ``t0``; :meth:`run` continues where it stopped.

    The per-pixel thresholds, hot pixels and initial charges are drawn from ``rng`` here, so one
    simulator is one sensor. Fully vectorised over pixels; loops over frames only.
    """

    def __init__(
        self,
        scene: Scene,
        sensor: SensorConfig | None = None,
        rng: np.random.Generator | None = None,
        t0: float = 0.0,
        substeps: int = 4,
    ):
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.scene, self.sensor = scene, sensor or SensorConfig.ideal()
        self.rng = rng if rng is not None else np.random.default_rng()
        self.t, self.substeps = float(t0), int(substeps)
        shape = (scene.height, scene.width)
        s = self.sensor
        relative = 1 + s.threshold_mismatch * self.rng.standard_normal(shape)
        self.threshold = (s.threshold * np.maximum(relative, 0.2)).astype(np.float32)
        hot = self.rng.uniform(size=shape) < s.hot_pixel_fraction
        # dark and hot-pixel charge per frame: exactly their rate in spikes/frame at this pixel
        self.dark = (self.threshold * (s.dark_current + s.hot_pixel_rate * hot)).astype(np.float32)
        self.charge = self.threshold * self.rng.uniform(size=shape).astype(np.float32)

    def run(self, n_frames: int) -> np.ndarray:
        """The next ``n_frames`` spike frames as ``(T, H, W) uint8`` 0/1, upright."""
        h, w = self.charge.shape
        spikes = np.empty((n_frames, h, w), np.uint8)
        chunk = max(1, RENDER_BUDGET // (self.substeps * h * w))
        for start in range(0, n_frames, chunk):
            n = min(chunk, n_frames - start)
            charge_in = self._charge_in(self.t + start, n)
            for i in range(n):
                self.charge += charge_in[i]
                fired = self.charge >= self.threshold
                np.subtract(self.charge, self.threshold, out=self.charge, where=fired)
                np.minimum(self.charge, self.threshold, out=self.charge)
                spikes[start + i] = fired
        self.t += n_frames
        return spikes

    def _charge_in(self, t: float, n: int) -> np.ndarray:
        """Charge ``(n, H, W) float32`` collected in frames starting at ``t, t+1, ...``."""
        s, h, w = self.substeps, self.scene.height, self.scene.width
        times = substep_times(t, n, s)
        light = self.scene.intensities(times).reshape(n, s, h, w).mean(1)
        charge = np.float32(SPIKE_RATE) * light + self.dark
        if self.sensor.shot_noise:
            quantum = self.sensor.threshold / self.sensor.photons_per_threshold  # charge/photon
            charge = (self.rng.poisson(charge / quantum) * quantum).astype(np.float32)
        return charge


def simulate(
    scene: Scene,
    n_frames: int,
    sensor: SensorConfig | None = None,
    rng: np.random.Generator | None = None,
    t0: float = 0.0,
    substeps: int = 4,
) -> np.ndarray:
    """Film ``n_frames`` frames of ``scene`` from time ``t0`` with ``sensor`` (None: ideal).

    Returns ``(T, H, W) uint8`` 0/1, upright; frame ``k`` covers ``[t0 + k, t0 + k + 1)``.
    """
    return SpikeSimulator(scene, sensor, rng, t0, substeps).run(n_frames)


def ground_truth(scene: Scene, frames: Sequence[float], t0: float = 0.0) -> np.ndarray:
    """Ground truth of ``frames`` (N,) as ``(N, H, W) float32`` linear intensity in [0, 1]: the
    scene at ``t0 + k + 0.5``, the middle of frame ``k``'s interval."""
    return np.array(scene.intensities(np.asarray(frames, np.float64) + t0 + 0.5), np.float32)


def training_sample(
    rng: np.random.Generator,
    height: int,
    width: int,
    sensor: SensorConfig | None = None,
    motion: str | None = None,
    brightness: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One training pair: a random scene filmed for a 41-frame window centred at frame 20.

    ``sensor`` None draws one with :meth:`SensorConfig.random` (ideal or real-like, so a model
    learns both regimes); ``motion``/``brightness`` None are drawn by :func:`random_scene`.
    Returns ``spikes (41, H, W) uint8`` and ``gt (5, H, W) float32``, the ground truth at the
    five block centres, frames 6, 13, 20, 27 and 34.
    """
    spikes, gt, _ = filmed_sample(rng, height, width, sensor, motion, brightness)
    return spikes, gt


def filmed_sample(
    rng: np.random.Generator,
    height: int,
    width: int,
    sensor: SensorConfig | None = None,
    motion: str | None = None,
    brightness: str | None = None,
) -> tuple[np.ndarray, np.ndarray, SensorConfig]:
    """:func:`training_sample` (same draws from ``rng``, same arrays) and the sensor it used."""
    scene = random_scene(rng, height, width, motion, brightness)
    sensor = sensor or SensorConfig.random(rng)
    return simulate(scene, FILM_FRAMES, sensor, rng), ground_truth(scene, GT_FRAMES), sensor
