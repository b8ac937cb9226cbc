"""Training batches from the project's simulator: 41-frame windows and ground truth at the five
block centres, with random 90° rotations and flips.

Every batch is a pure function of ``(seed, rank, step)``, so a resumed run sees exactly the
batches it would have seen, and each data-parallel rank sees different ones.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from spk2img.core.simulator import training_sample


def _sample(seed: int, index: int, patch: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``index`` of stream ``seed``: ``(41, P, P) uint8``, ``(5, P, P) float32``."""
    return training_sample(np.random.default_rng([seed, index]), patch, patch)


def augment(spikes: np.ndarray, truth: np.ndarray, rng: np.random.Generator):
    """The same random rotation by k·90° and optional flip on both ``(c, h, w)`` arrays."""
    k = int(rng.integers(4))
    spikes, truth = np.rot90(spikes, k, axes=(1, 2)), np.rot90(truth, k, axes=(1, 2))
    if rng.integers(2):
        spikes, truth = spikes[:, :, ::-1], truth[:, :, ::-1]
    return spikes, truth


class SimulatedBatches:
    """``batch(step)`` -> ``(spikes (B, 41, P, P) float32, truth (B, 5, P, P) float32)`` tensors.

    With ``cache_size`` > 0 a pool of that many samples is simulated once (and kept, bit-packed,
    under ``cache_dir`` when given) and batches draw from it; with 0 every sample is new.
    """

    def __init__(
        self,
        patch: int,
        batch_size: int,
        seed: int,
        rank: int = 0,
        cache_size: int = 0,
        cache_dir: str | Path | None = None,
    ):
        if patch % 4:
            raise ValueError(f"patch must be a multiple of 4 (the pyramid's), got {patch}")
        self.patch, self.batch_size, self.seed, self.rank = patch, batch_size, seed, rank
        self.cache = self._load_or_build_cache(cache_size, cache_dir) if cache_size else None

    def _load_or_build_cache(self, size: int, cache_dir: str | Path | None):
        path = None
        if cache_dir is not None:
            path = Path(cache_dir) / f"cache_seed{self.seed}_r{self.rank}_p{self.patch}_n{size}.npz"
            if path.is_file():
                with np.load(path) as z:
                    return z["spikes"], z["truth"]
        p = self.patch
        spikes = np.empty((size, 41 * p * p // 8), np.uint8)
        truth = np.empty((size, 5, p, p), np.float32)
        for i in tqdm(range(size), desc="simulating training cache", unit="sample"):
            s, t = _sample(self.seed * 1000 + self.rank, i, p)
            spikes[i] = np.packbits(s.reshape(-1))
            truth[i] = t
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, spikes=spikes, truth=truth)
        return spikes, truth

    def _cached(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        packed, truth = self.cache
        p = self.patch
        bits = np.unpackbits(packed[index], count=41 * p * p)
        return bits.reshape(41, p, p), truth[index]

    def batch(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.rank, step])
        spikes, truth = [], []
        for j in range(self.batch_size):
            if self.cache is not None:
                s, t = self._cached(int(rng.integers(len(self.cache[1]))))
            else:
                index = 10**7 + step * self.batch_size + j  # never a cache index
                s, t = _sample(self.seed * 1000 + self.rank, index, self.patch)
            s, t = augment(s, t, rng)
            spikes.append(np.ascontiguousarray(s, np.float32))
            truth.append(np.ascontiguousarray(t, np.float32))
        return torch.from_numpy(np.stack(spikes)), torch.from_numpy(np.stack(truth))
