"""The bounded reconstruction pool: CPU work off the event loop, and admission control.

``workers`` threads run jobs (decoding, TFP/TFI, the model, PNG encoding). A request holds an
:class:`Admission` from its arrival until its last job has finished and runs one job at a time,
so at most ``workers`` jobs run and at most ``max_queue`` wait: a request that finds
``workers + max_queue`` admissions taken is turned away (503) before its body is read.

Each admission also reserves an estimate of the memory its request may use (see
:func:`spk2img.service.reconstruction.job_memory`); a request whose estimate does not fit in
what is left of ``budget`` bytes is turned away too. The reservation is given back with the
place, once the request's last job has finished. Soon after the last admission is given back
the pool returns the memory its requests freed to the system (:mod:`spk2img.runtime.allocator`).
"""

from __future__ import annotations

import asyncio
import gc
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from spk2img.runtime.allocator import release_free_memory

T = TypeVar("T")
IDLE_TRIM_SECONDS = 0.5
"""How long after the last admission is given back the pool returns freed memory (the
request's response and buffers are dropped by then)."""


class InferencePool:
    """A thread pool of ``workers`` threads admitting ``workers + max_queue`` requests at once,
    whose memory estimates add up to at most ``budget`` bytes (0: no budget)."""

    def __init__(self, workers: int, max_queue: int, budget: int = 0):
        self.capacity = workers + max_queue
        self.budget = budget
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="spk2img-job")
        self._lock = threading.Lock()
        self._admitted = 0
        self._reserved = 0
        self._jobs = 0

    @property
    def reserved(self) -> int:
        """Bytes reserved by the admitted requests."""
        return self._reserved

    @property
    def admitted(self) -> int:
        """Requests holding an admission."""
        return self._admitted

    @property
    def jobs(self) -> int:
        """Jobs submitted and not finished (running or queued)."""
        return self._jobs

    def full(self, smallest: int = 0) -> bool:
        """Whether no request could be admitted now: every place taken, or not ``smallest``
        bytes (the least a request reserves) left of the budget."""
        return self._refusal(smallest) is not None

    def admit(self, cost: int = 0) -> Admission | str:
        """An admission for one request reserving ``cost`` bytes, or why there is none:
        ``"busy"`` (``capacity`` taken) or ``"memory"`` (over the budget)."""
        with self._lock:
            refusal = self._refusal(cost)
            if refusal is not None:
                return refusal
            self._admitted += 1
            self._reserved += cost
        return Admission(self, cost)

    def _refusal(self, cost: int) -> str | None:
        if self._admitted >= self.capacity:
            return "busy"
        if self.budget and self._reserved + cost > self.budget:
            return "memory"
        return None

    async def run(self, fn: Callable[..., T], *args) -> T:
        """Run ``fn(*args)`` in the pool (outside an admission: start-up work)."""
        return await asyncio.wrap_future(self._submit(fn, *args))

    def shutdown(self) -> None:
        """Drop queued jobs; running ones finish in their threads."""
        self._executor.shutdown(wait=False, cancel_futures=True)

    def _submit(self, fn: Callable[..., T], *args) -> Future[T]:
        with self._lock:
            self._jobs += 1
        future = self._executor.submit(fn, *args)
        future.add_done_callback(self._job_done)
        return future

    def _job_done(self, _: Future) -> None:
        with self._lock:
            self._jobs -= 1

    def _release(self, cost: int) -> None:
        with self._lock:
            self._admitted -= 1
            self._reserved -= cost
            idle = self._admitted == 0
        if idle:  # once the request's objects are gone too, give their memory back
            timer = threading.Timer(IDLE_TRIM_SECONDS, self._release_memory_if_idle)
            timer.daemon = True
            timer.start()

    def _release_memory_if_idle(self) -> None:
        if self._admitted == 0:
            gc.collect()  # cycles (exceptions' tracebacks hold frames and their arrays)
            release_free_memory()


class Admission:
    """One request's place in the pool: :meth:`run` its jobs one at a time, then :meth:`close`."""

    def __init__(self, pool: InferencePool, cost: int = 0):
        self._pool, self._cost = pool, cost
        self._last: Future | None = None
        self._closed = False

    async def run(self, fn: Callable[..., T], *args) -> T:
        """Run ``fn(*args)`` in the pool and wait for it. If the wait is cancelled (the client
        left, the time ran out) a job already running still finishes in its thread."""
        if self._last is not None and not self._last.done():
            raise RuntimeError("one job at a time per admission")
        self._last = self._pool._submit(fn, *args)
        return await asyncio.wrap_future(self._last)

    def close(self) -> None:
        """Give the place back once the last job is over (at once if it is)."""
        if self._closed:
            return
        self._closed = True
        if self._last is None:
            self._pool._release(self._cost)
        else:  # called at once when the job is already done
            self._last.add_done_callback(lambda _: self._pool._release(self._cost))
