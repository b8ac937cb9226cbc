"""Timers: the median of repeated calls after a warm-up, and the machine's fp32 matmul rate."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import TypeVar

MATMUL_SIZE = 1024
T = TypeVar("T")


def call_seconds(call: Callable[[], T], repeats: int, warmup: int = 1) -> tuple[list[float], T]:
    """Wall seconds of each of ``repeats`` calls of ``call`` after ``warmup`` untimed calls,
    and what the last call returned."""
    for _ in range(warmup):
        call()
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        seconds.append(time.perf_counter() - start)
    return seconds, result


def median_ms(seconds: list[float]) -> float:
    """The median of ``seconds`` in milliseconds."""
    return 1000.0 * statistics.median(seconds)


def matmul_gflops(threads: int, repeats: int, size: int = MATMUL_SIZE) -> float:
    """fp32 GFLOP/s of a ``size x size`` matrix product in PyTorch on ``threads`` threads:
    ``2 * size**3`` FLOPs over the median time (the machine's practical dense-compute peak)."""
    import torch

    torch.set_num_threads(threads)
    generator = torch.Generator().manual_seed(0)
    a = torch.rand(size, size, generator=generator)
    b = torch.rand(size, size, generator=generator)
    seconds, _ = call_seconds(lambda: torch.mm(a, b), repeats, warmup=2)
    return 2 * size**3 / statistics.median(seconds) / 1e9
