"""Soak ``spk2img serve`` with good, junk, trickling and resetting clients at once.

``python scripts/service_soak.py [--model tiny] [--clients 8] [--requests 50] [--size 32]``
starts the real service on a free port (``--upload-read-timeout-seconds 1``, so tricklers end
soon) and runs ``--clients`` threads of ``--requests`` requests each, drawn at random: 70 % good
(a random stream, random centres or stride, a method: every frame must equal in-process
``spk2img.reconstruct`` to float32 rounding, and ``DONE`` must end the stream; a 503 is
retried), 15 % junk (bad parameters, repeated ones, a wrong length: must be a 4xx JSON), 5 %
trickling (a byte every 0.3 s: must end in 408) and 10 % resetting mid-upload. At the end no
place may stay taken and the process's resident memory is reported before and after. Exit 0 when
every expectation held, 1 otherwise, with a summary line per kind.
"""

from __future__ import annotations

import argparse
import random
import select
import socket
import struct
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

import spk2img
from spk2img.bench.serve_process import serve_process
from spk2img.io.spikes import pack_frames
from spk2img.protocol.framing import DoneRecord, FrameRecord, RecordParser

OCTET = {"Content-Type": "application/octet-stream"}


def resident_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class Soak:
    def __init__(self, url: str, model: str, size: int):
        self.url, self.model, self.size = url, model, size
        self.outcomes: Counter = Counter()
        self.failures: list[str] = []
        self.lock = threading.Lock()

    def note(self, kind: str, ok: bool, why: str = "") -> None:
        with self.lock:
            self.outcomes[(kind, ok)] += 1
            if not ok:
                self.failures.append(f"{kind}: {why}")

    def good(self, rng: random.Random) -> None:
        frames = rng.randint(45, 120)
        spikes = (
            np.random.default_rng(rng.randrange(2**31)).random((frames, self.size, self.size))
            < rng.uniform(0.05, 0.6)
        ).astype(np.uint8)
        method = rng.choice(["net", "tfp", "tfi"])
        stride = rng.choice([3, 7, 10])
        query = f"height={self.size}&width={self.size}&stride={stride}&method={method}"
        for _ in range(50):
            answer = httpx.post(
                f"{self.url}/v1/reconstruct?{query}",
                content=pack_frames(spikes),
                headers=OCTET,
                timeout=120,
            )
            if answer.status_code != 503:
                break
            time.sleep(0.2)
        if answer.status_code != 200:
            return self.note("good", False, f"{answer.status_code} {answer.text[:200]}")
        parser = RecordParser()
        records = parser.feed(answer.content)
        parser.finish()
        got = {r.center: r.image for r in records if isinstance(r, FrameRecord)}
        if not records or not isinstance(records[-1], DoneRecord):
            return self.note("good", False, "no DONE record")
        kwargs = {"model": self.model} if method == "net" else {}
        expected = spk2img.reconstruct(spikes, stride=stride, method=method, threads=1, **kwargs)
        same = list(got) == expected.centers.tolist() and all(
            np.allclose(got[c], f, atol=1e-5)
            for c, f in zip(expected.centers, expected.frames, strict=True)
        )
        self.note("good", same, "" if same else f"frames differ ({method}, stride {stride})")

    def junk(self, rng: random.Random) -> None:
        target = rng.choice(
            [
                "/v1/reconstruct?height=0&width=8&stride=3",
                "/v1/reconstruct?method=tfp&method=tfi&height=8&width=8&stride=3",
                "/v1/reconstruct?height=8&width=8",
                "/v1/reconstruct?height=8&width=8&stride=3&method=nope",
                "/v1/reconstruct?height=8&width=8&stride=3&binning=2&binning=3",
            ]
        )
        answer = httpx.post(self.url + target, content=b"\0" * rng.randint(1, 999), headers=OCTET)
        ok = 400 <= answer.status_code < 500 and "detail" in answer.json()
        self.note("junk", ok, f"{target}: {answer.status_code}")

    def _raw(self, length: int) -> socket.socket:
        port = int(self.url.rsplit(":", 1)[1])
        sock = socket.create_connection(("127.0.0.1", port), timeout=30)
        head = (
            f"POST /v1/reconstruct?height={self.size}&width={self.size}&stride=3&method=tfp "
            f"HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
            f"Content-Length: {length}\r\n\r\n"
        )
        sock.sendall(head.encode())
        return sock

    def trickle(self, rng: random.Random) -> None:
        sock = self._raw(60 * self.size * self.size // 8)
        answer = b""
        try:
            for _ in range(40):  # a byte every 0.3 s until the service answers
                sock.sendall(b"\0")
                if select.select([sock], [], [], 0.3)[0]:
                    break
            answer = sock.recv(4096)
        except OSError:
            pass
        finally:
            sock.close()
        head = answer[:40].decode(errors="replace")
        self.note("trickle", answer.startswith(b"HTTP/1.1 408"), head)

    def reset(self, rng: random.Random) -> None:
        sock = self._raw(200 * self.size * self.size // 8)
        sock.sendall(b"\0" * rng.randint(1, 50 * self.size * self.size // 8))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()
        self.note("reset", True)

    def client(self, seed: int, requests: int) -> None:
        rng = random.Random(seed)
        kinds = [self.good] * 14 + [self.junk] * 3 + [self.trickle] + [self.reset] * 2
        for _ in range(requests):
            try:
                rng.choice(kinds)(rng)
            except Exception as exc:  # noqa: BLE001 - every surprise is a failure to report
                self.note("error", False, repr(exc))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="tiny")
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--requests", type=int, default=50)
    parser.add_argument("--size", type=int, default=32)
    args = parser.parse_args()
    flags = ("--threads", "2", "--upload-read-timeout-seconds", "1")
    with serve_process(args.model, *flags) as server:
        url = server.url
        before = resident_mib(server.process.pid)
        soak = Soak(url, args.model, args.size)
        start = time.monotonic()
        threads = [
            threading.Thread(target=soak.client, args=(k, args.requests))
            for k in range(args.clients)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        time.sleep(1.0)
        admitted = [
            line
            for line in httpx.get(url + "/metrics").text.splitlines()
            if line.startswith("spk2img_admitted_requests ")
        ]
        after = resident_mib(server.process.pid)
    free = admitted == ["spk2img_admitted_requests 0.0"]
    for kind in ("good", "junk", "trickle", "reset", "error"):
        ok, bad = soak.outcomes[(kind, True)], soak.outcomes[(kind, False)]
        if ok or bad:
            print(f"{kind}: {ok} as expected, {bad} not")
    for failure in soak.failures[:20]:
        print("  failed:", failure)
    print(
        f"{time.monotonic() - start:.0f} s; places all free after: {free}; "
        f"RSS {before:.0f} -> {after:.0f} MiB"
    )
    return 0 if free and not soak.failures else 1


if __name__ == "__main__":
    sys.exit(main())
