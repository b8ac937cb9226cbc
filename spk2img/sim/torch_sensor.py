"""The spike camera's sensor in torch, batched, on the device a model trains on.

:func:`film` is :class:`spk2img.sim.simulator.SpikeSimulator` for a batch of windows, each
with its own :class:`~spk2img.sim.simulator.SensorConfig`: the same integrate-and-fire (the
same float32 steps, so given the same light and initial state the spikes are identical), the
same per-pixel draws (threshold mismatch, hot pixels, initial charge) and the same noises
(photon shot noise, dark current, hot pixels), drawn from a torch generator instead of numpy's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from spk2img.io.light import SPIKE_RATE
from spk2img.sim.simulator import SensorConfig


@dataclass
class SensorState:
    """Per-pixel state of a batch of sensors, ``(B, H, W) float32`` each."""

    threshold: torch.Tensor
    dark: torch.Tensor
    """Charge per frame from dark current and hot pixels (their rates times the threshold)."""
    charge: torch.Tensor

    @classmethod
    def draw(
        cls,
        sensors: Sequence[SensorConfig],
        height: int,
        width: int,
        generator: torch.Generator,
        device: torch.device,
    ) -> SensorState:
        """The per-pixel draws of ``SpikeSimulator.__init__`` for each of ``sensors``:
        thresholds with mismatch (at least 0.2 of nominal), hot pixels, initial charge uniform
        in [0, threshold)."""
        b = len(sensors)

        def column(values) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=device)[:, None, None]

        shape = (b, height, width)
        nominal = column([s.threshold for s in sensors])
        mismatch = column([s.threshold_mismatch for s in sensors])
        normal = torch.randn(shape, generator=generator, device=device)
        threshold = nominal * torch.clamp(1 + mismatch * normal, min=0.2)
        uniform = torch.rand(shape, generator=generator, device=device)
        hot = uniform < column([s.hot_pixel_fraction for s in sensors])
        rate = column([s.dark_current for s in sensors])
        rate = rate + column([s.hot_pixel_rate for s in sensors]) * hot
        charge = threshold * torch.rand(shape, generator=generator, device=device)
        return cls(threshold, threshold * rate, charge)


def film(
    light: torch.Tensor,
    sensors: Sequence[SensorConfig],
    generator: torch.Generator,
    state: SensorState | None = None,
) -> torch.Tensor:
    """Spike frames of a batch of windows.

    Args:
        light: ``(B, T, S, H, W) float32`` intensity in [0, 1] at the ``S`` substep midpoints
            of each of the ``T`` frame intervals (the simulator's midpoint rule).
        sensors: the sensor of each window (B).
        generator: the torch generator of every random draw (on ``light``'s device).
        state: the sensors' per-pixel state (None: drawn with :meth:`SensorState.draw`).

    Returns:
        ``(B, T, H, W) uint8`` 0/1 spikes.
    """
    b, t, s, h, w = light.shape
    if state is None:
        state = SensorState.draw(sensors, h, w, generator, light.device)
    summed = light[:, :, 0]
    for k in range(1, s):  # in order, as numpy's mean over the substep axis adds them
        summed = summed + light[:, :, k]
    charge_in = SPIKE_RATE * (summed / s) + state.dark[:, None]
    shot = [i for i, sensor in enumerate(sensors) if sensor.shot_noise]
    if shot:
        quantum = torch.tensor(
            [sensors[i].threshold / sensors[i].photons_per_threshold for i in shot],
            dtype=torch.float32,
            device=light.device,
        )[:, None, None, None]
        photons = torch.poisson(charge_in[shot] / quantum, generator=generator)
        charge_in[shot] = photons * quantum
    charge, threshold = state.charge.clone(), state.threshold
    spikes = torch.empty((b, t, h, w), dtype=torch.uint8, device=light.device)
    for frame in range(t):
        charge += charge_in[:, frame]
        fired = charge >= threshold
        charge -= threshold * fired
        charge = torch.minimum(charge, threshold)
        spikes[:, frame] = fired
    return spikes
