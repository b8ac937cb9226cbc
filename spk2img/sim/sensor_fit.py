"""Estimate a real sensor's noises from a capture of a still scene (docs/sensor.md).

The capture is ``(T, H, W)`` 0/1 spikes of a scene that does not move. Per pixel, the firing
rate ``r`` (spikes/frame) and the inter-spike intervals (ISIs) are measured, and the four noises
of :class:`~spk2img.sim.simulator.SensorConfig` are estimated as follows.

- **Hot pixels**: pixels whose rate exceeds the median of their 8 neighbours by more than
  ``max(HOT_MIN_EXCESS, HOT_SIGMAS x`` the robust spread of that excess over all pixels);
  the fraction of such pixels and the median of their excess (spikes/frame).
- **Shot noise**: an ideal integrate-and-fire pixel under constant light fires at a constant
  interval (up to one frame of read-out quantisation); with ``n`` photons per threshold the
  time to collect a threshold is Gamma-distributed, ISI CV² = 1/n. ``n`` is 1 / the median, over
  pixels with at least :data:`MIN_INTERVALS` intervals, of the ISI CV² less the quantisation's
  share (1/6 frame² over the squared mean interval).
- **Threshold mismatch**: a pixel's rate is its light over its threshold, so in flat parts of
  the scene the relative deviation of its rate from its neighbours' median is the mismatch
  plus noise. Rates are taken from the mean ISI (far finer than spike counts over a short
  capture); the mismatch is the square root of the robust (interquartile) variance of that
  deviation over the flattest quarter of the pixels, less the ISI noise's variance (CV² over
  the number of intervals, for the pixel and its neighbours' median).
- **Dark current**: it cannot be told apart from light without a dark frame; the darkest pixels
  fire at least the dark rate, so the 0.5th percentile of the (non-hot) neighbourhood-median
  rate bounds it from above; the preset takes half that bound (the middle of what the capture
  allows) and records the bound, which training draws the dark current below.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from spk2img.sim.simulator import SensorConfig

FITTED_PRESET = Path(__file__).resolve().parents[1] / "assets" / "sensors" / "vidar-fitted.json"
"""The preset fitted to the real PKU capture this project tests on (docs/sensor.md)."""
HOT_MIN_EXCESS = 0.05
"""Spikes/frame above the neighbours' median below which no pixel counts as hot."""
HOT_SIGMAS = 8.0
MIN_INTERVALS = 3
MIN_USABLE_PIXELS = 16
"""Pixels with :data:`MIN_INTERVALS` intervals needed for a fit (its percentiles and medians)."""
DARK_PERCENTILE = 0.5


def neighbour_median(image: np.ndarray) -> np.ndarray:
    """Median of each pixel's 8 neighbours (borders mirrored), ``(H, W)`` -> ``(H, W)``."""
    padded = np.pad(image, 1, mode="reflect")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (3, 3)).reshape(*image.shape, 9)
    return np.median(np.delete(windows, 4, axis=-1), axis=-1)


def interval_statistics(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel: the number of inter-spike intervals, their mean (frames) and the unbiased
    estimate of their squared coefficient of variation (NaN with fewer than two intervals):
    three ``(H, W)`` arrays."""
    fired = spikes.astype(bool)
    intervals = np.maximum(fired.sum(0) - 1, 0)
    last = np.full(spikes.shape[1:], -1.0)
    s1 = np.zeros(spikes.shape[1:])
    s2 = np.zeros(spikes.shape[1:])
    for k, now in enumerate(fired):
        gap = np.where(now & (last >= 0), k - last, 0.0)
        s1 += gap
        s2 += gap * gap
        last = np.where(now, k, last)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / intervals
        var = (s2 - intervals * mean**2) / (intervals - 1)
        cv2 = np.where(intervals >= 2, var / mean**2, np.nan)
    return intervals, mean, cv2


def fit_sensor(spikes: np.ndarray) -> tuple[SensorConfig, dict]:
    """Estimate the sensor from ``(T, H, W)`` 0/1 spikes of a still scene (module doc).

    Returns the preset and a report of the measurements behind it (JSON-able)."""
    spikes = np.asarray(spikes)
    if spikes.ndim != 3 or spikes.shape[0] < 20:
        raise ValueError(f"need (T, H, W) spikes with T >= 20, got shape {spikes.shape}")
    t = spikes.shape[0]
    rate = spikes.mean(0, dtype=np.float64)
    local = neighbour_median(rate)
    excess = rate - local
    spread = 1.4826 * np.median(np.abs(excess - np.median(excess)))
    hot = excess > max(HOT_MIN_EXCESS, HOT_SIGMAS * spread)
    hot_rate = float(np.median(excess[hot])) if hot.any() else 0.0

    intervals, mean_interval, cv2 = interval_statistics(spikes)
    usable = (intervals >= MIN_INTERVALS) & ~hot & np.isfinite(cv2)
    if usable.sum() < MIN_USABLE_PIXELS:
        raise ValueError(
            f"only {int(usable.sum())} pixels (hot ones aside) fire at least {MIN_INTERVALS} "
            f"times, and a fit needs {MIN_USABLE_PIXELS}: record longer or with more light"
        )
    quantisation = (1 / 6) / mean_interval**2  # read-out at frame ends: uniform +-1/2 frame
    excess_cv2 = (cv2 - quantisation)[usable]
    shot_cv2 = float(np.mean(np.clip(excess_cv2, *np.percentile(excess_cv2, [1, 99]))))
    photons = 1 / shot_cv2 if shot_cv2 > 1e-4 else 1e4

    # mismatch: the interval-based rate is far finer than counts over a short capture
    isi_rate = np.where(usable, 1 / np.where(usable, mean_interval, 1), np.nan)
    local_isi = neighbour_median(np.nan_to_num(isi_rate, nan=float(np.nanmedian(isi_rate))))
    roughness = neighbour_median(np.abs(rate - local))
    flat = usable & (roughness <= np.quantile(roughness[usable], 0.25))
    relative = isi_rate[flat] / local_isi[flat] - 1
    q1, q3 = np.percentile(relative, [25, 75])
    robust_var = float(((q3 - q1) / 1.349) ** 2)
    # a pixel's and its neighbours' median's interval noise (the median of 8: ~(pi/2)/8 of it)
    counting = float(np.mean(max(shot_cv2, 0.0) / intervals[flat])) * (1 + np.pi / 16)
    mismatch = float(np.sqrt(max(0.0, robust_var - counting)))

    dark_upper = float(np.percentile(local[~hot], DARK_PERCENTILE))
    sensor = SensorConfig(
        shot_noise=True,
        photons_per_threshold=float(photons),
        dark_current=dark_upper / 2,
        threshold_mismatch=mismatch,
        hot_pixel_fraction=float(hot.mean()),
        hot_pixel_rate=hot_rate,
    )
    report = {
        "frames": t,
        "height": int(spikes.shape[1]),
        "width": int(spikes.shape[2]),
        "mean_rate": float(rate.mean()),
        "rate_percentiles": dict(
            zip(["1", "50", "99"], np.percentile(rate, [1, 50, 99]).tolist(), strict=True)
        ),
        "hot_pixels": int(hot.sum()),
        "hot_threshold": float(max(HOT_MIN_EXCESS, HOT_SIGMAS * spread)),
        "isi_pixels": int(usable.sum()),
        "isi_cv2_median": shot_cv2,
        "flat_pixels": int(flat.sum()),
        "relative_deviation_var": float(robust_var),
        "counting_var": counting,
        "dark_current_upper_bound": dark_upper,
    }
    return sensor, report


def save_preset(path: str | Path, sensor: SensorConfig, report: dict, source: str) -> None:
    """Write a sensor preset: the :class:`SensorConfig` fields, where they came from, and the
    measurements behind them."""
    preset = {"sensor": asdict(sensor), "source": source, "report": report}
    Path(path).write_text(json.dumps(preset, indent=2) + "\n")


def load_preset(path: str | Path) -> SensorConfig:
    """The :class:`SensorConfig` of a preset written by :func:`save_preset`."""
    try:
        data = json.loads(Path(path).read_text())
        return SensorConfig(**data["sensor"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a sensor preset ({exc})") from exc
