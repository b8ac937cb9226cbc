"""The service under load: frames/s and latency over HTTP against the same model in-process.

The real ``spk2img serve`` runs in a subprocess on a free port of 127.0.0.1 with ``--threads T``
(its default: ``T`` workers of one onnxruntime thread each). Each request uploads one 41-frame
window and gets its centre frame back through :class:`~spk2img.clients.Client`. The in-process
baseline runs the same graph, loaded as the service loads it, with one thread
in a pool of ``T`` threads fed by as many concurrent callers — the service minus HTTP.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np

from spk2img.sim.simulator import CENTER_FRAME

from .serve_process import serve_process
from .worker import thread_env

PERCENTILES = (50, 90, 99)


def drive(make_call: Callable[[], Callable[[], None]], clients: int, requests: int) -> dict:
    """Run ``requests`` calls from ``clients`` concurrent threads (each builds its own call with
    ``make_call`` and calls it in a loop); frames/s over the wall time and latency percentiles
    (ms) of the single calls."""
    latencies: list[float] = []
    lock = threading.Lock()
    shares = [requests // clients + (i < requests % clients) for i in range(clients)]
    failures: list[BaseException] = []

    def client(n: int) -> None:
        try:
            call = make_call()
            for _ in range(n):
                start = time.perf_counter()
                call()
                with lock:
                    latencies.append(time.perf_counter() - start)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the calling thread
            failures.append(exc)

    threads = [threading.Thread(target=client, args=(n,)) for n in shares]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    seconds = time.perf_counter() - start
    if failures:
        raise failures[0]
    ms = 1000.0 * np.asarray(latencies)
    return {
        "clients": clients,
        "requests": requests,
        "frames_per_s": requests / seconds,
        **{f"p{q}_ms": float(np.percentile(ms, q)) for q in PERCENTILES},
    }


def service_benchmark(
    model: Path,
    window: np.ndarray,
    threads: int,
    levels: tuple[int, ...],
    requests: int,
    device: str = "cpu",
) -> dict:
    """Load the service and the in-process model with ``window (41, H, W) uint8`` at each number
    of concurrent clients in ``levels``; ``overhead`` is in-process frames/s over the service's.
    ``device``: where both run; the service must report that it runs there (``/readyz``), else
    :class:`RuntimeError`."""
    from spk2img.runtime.loader import load_network

    batch = window[None].astype(np.float32)
    # the service's intra-op threads: T // T workers; warmed up as the service is before ready
    local_model = load_network(model, device=device, threads=1, block_reuse=False).predict
    local_model(batch)  # and on this window's size
    jobs = ThreadPoolExecutor(threads)  # like the service's pool: T jobs at once, FIFO queue

    def local_call() -> Callable[[], None]:
        return lambda: jobs.submit(local_model, batch).result()

    results = []
    env = {**os.environ, **thread_env(threads)}
    flags = ("--threads", str(threads), "--device", device)
    with serve_process(model, *flags, env=env) as server:
        url = server.url
        provider = served_provider(url)
        if provider != local_model.provider:
            raise RuntimeError(
                f"the service runs the model on {provider}, not {local_model.provider}"
            )
        http_call = partial(http_caller, url, window)
        drive(http_call, 1, 2)  # warm-up: the first requests' code paths
        for clients in levels:
            service = drive(http_call, clients, requests)
            local = drive(local_call, clients, requests)
            overhead = local["frames_per_s"] / service["frames_per_s"]
            results.append(
                {"clients": clients, "service": service, "in_process": local, "overhead": overhead}
            )
    jobs.shutdown()
    return {
        "model": str(model),
        "provider": provider,
        "threads": threads,
        "height": int(window.shape[1]),
        "width": int(window.shape[2]),
        "levels": results,
    }


def served_provider(url: str) -> str:
    """The onnxruntime provider the service at ``url`` reports in ``/readyz`` (a service that
    does not report one runs on the CPU)."""
    import httpx

    return httpx.get(url + "/readyz", timeout=10).json().get("provider", "CPUExecutionProvider")


def http_caller(url: str, window: np.ndarray) -> Callable[[], None]:
    """A call that uploads ``window (41, H, W)`` as a ``.dat`` body and reads its centre frame
    back (one client per calling thread, no retries)."""
    from spk2img.clients import Client
    from spk2img.io.spikes import pack_frames

    client = Client(url, retries=0)
    body, (height, width) = pack_frames(window), window.shape[1:]

    def call() -> None:
        frames = list(client.reconstruct(body, height, width, centers=[CENTER_FRAME]))
        if len(frames) != 1:
            raise RuntimeError(f"the service sent {len(frames)} frames, not 1")

    return call
