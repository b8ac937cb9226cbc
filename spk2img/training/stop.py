"""Stopping a training run between optimiser steps without losing any.

The first SIGINT (Ctrl-C) or SIGTERM asks the run to stop after the step in progress; the run
then writes ``last.pt`` at that step and ends, and the same command resumes it. A second signal
a second or more later stops at once (a ``KeyboardInterrupt``), losing the steps since the last
checkpoint; one sooner is the same request again (``timeout`` sends its signal to the command
and then to the command's process group, which holds the command too).
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import torch
import torch.distributed as dist

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Catches :data:`SIGNALS` while entered (in the main thread only; elsewhere it never asks
    to stop). ``signal`` is the first one received, or None; one that comes ``again_after_s``
    seconds or more after it raises ``KeyboardInterrupt``."""

    def __init__(self, again_after_s: float = 1.0) -> None:
        self.signal: signal.Signals | None = None
        self.again_after_s = again_after_s
        self._first_at = 0.0
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
            if time.monotonic() - self._first_at >= self.again_after_s:
                raise KeyboardInterrupt
            return
        self.signal, self._first_at = signal.Signals(number), time.monotonic()
        print(
            f"spk2img train: {self.signal.name}: stopping after this step, which is then saved "
            "(again, a second or more later: stop at once)",
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
