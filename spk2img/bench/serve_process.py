"""``spk2img serve`` in a child process on a free port of 127.0.0.1: the real command line, as a
user starts it, for the load benchmark, the soak script and the service tests."""

from __future__ import annotations

import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

START_TIMEOUT_S = 120
"""How long a server may take to answer ``/readyz`` with 200 (seconds)."""

LOG_TAIL_CHARS = 4000
"""How much of an exited server's output its error quotes (characters, the last ones)."""


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@dataclass
class ServeProcess:
    """A running ``spk2img serve``: its base URL, port and process."""

    url: str
    port: int
    process: subprocess.Popen

    def get(self, path: str):
        """``GET url + path`` (an ``httpx.Response``; 10 s timeout)."""
        import httpx

        return httpx.get(self.url + path, timeout=10)


@contextmanager
def serve_process(
    model: str | Path,
    *flags: str,
    program: Sequence[str] = (sys.executable, "-m", "spk2img"),
    env: dict[str, str] | None = None,
    cwd: Path | None = None,
    timeout_s: float = START_TIMEOUT_S,
) -> Iterator[ServeProcess]:
    """Run ``PROGRAM serve --model MODEL --host 127.0.0.1 --port P --log-level warning FLAGS…``
    (environment ``env`` and folder ``cwd``, default this process's) and yield it once
    ``/readyz`` answers 200; terminate it afterwards (killed if it takes over 10 s).

    Raises ``RuntimeError`` with the end of its output if it exits first, or if it is not ready
    within ``timeout_s``."""
    port = free_port()
    cmd = [*program, "serve", "--model", str(model), "--host", "127.0.0.1", "--port", str(port)]
    cmd += ["--log-level", "warning", *flags]
    with tempfile.TemporaryFile() as log:  # a file, not a pipe: a full pipe would block it
        process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=cwd)
        server = ServeProcess(f"http://127.0.0.1:{port}", port, process)
        try:
            _wait_ready(server, log, timeout_s)
            yield server
        finally:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(10)


def _wait_ready(server: ServeProcess, log, timeout_s: float) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.process.poll() is not None:
            log.seek(0)
            out = log.read().decode(errors="replace")[-LOG_TAIL_CHARS:]
            raise RuntimeError(f"spk2img serve exited with {server.process.returncode}:\n{out}")
        try:
            if server.get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"spk2img serve not ready after {timeout_s:g} s")
