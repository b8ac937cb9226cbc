"""Stopping a training run between optimiser steps without losing any.

The first SIGINT (Ctrl-C) or SIGTERM asks the run to stop after the step in progress; the run
then writes ``last.pt`` at that step and ends, and the same command resumes it. A second signal
stops at once (a ``KeyboardInterrupt``), losing the steps since the last checkpoint.
"""

from __future__ import annotations

import signal
import sys
import threading

import torch
import torch.distributed as dist

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Catches :data:`SIGNALS` while entered (in the main thread only; elsewhere it never asks
    to stop). ``signal`` is the first one received, or None."""

    def __init__(self) -> None:
        self.signal: signal.Signals | None = None
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self._previous = {}

    def _handle(self, number: int, frame) -> None:
        if self.signal is not None:
            raise KeyboardInterrupt
        self.signal = signal.Signals(number)
        print(
            f"spk2img train: {self.signal.name}: stopping after this step, which is then saved "
            "(again: stop at once)",
            file=sys.stderr,
            flush=True,
        )

    @property
    def name(self) -> str:
        """The signal's name (``SIGINT``), or what stopped a replica that received none."""
        return self.signal.name if self.signal else "another process of the run"

    def agreed(self, world: int) -> bool:
        """Whether to stop now: asked here, or (``world`` > 1 processes of one data-parallel
        run) in any of them, so that every replica stops after the same step."""
        asked = self.signal is not None
        if world == 1:
            return asked
        flag = torch.tensor([int(asked)])
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        return bool(flag.item())
