"""An independent, deliberately plain implementation of docs/format.md (loops, no shared code),
used only by tests to check the package against the contract."""

from __future__ import annotations

import numpy as np


def encode_dat(frames: np.ndarray) -> bytes:
    """(T, H, W) 0/1 upright -> .dat: bottom row first, pixel p is bit p % 8 of byte p // 8."""
    t, h, w = frames.shape
    nbytes = (h * w + 7) // 8
    out = bytearray()
    for f in range(t):
        buf = bytearray(nbytes)
        for stored_row in range(h):
            row = h - 1 - stored_row  # stored bottom row first
            for col in range(w):
                if frames[f, row, col]:
                    p = stored_row * w + col
                    buf[p // 8] |= 1 << (p % 8)
        out += buf
    return bytes(out)


def tfp_reference(frames: np.ndarray, k: int, window: int) -> np.ndarray:
    half = window // 2
    return np.clip(frames[k - half : k + half + 1].astype(np.float64).mean(axis=0) / 0.6, 0, 1)


def tfi_reference(frames: np.ndarray, k: int) -> np.ndarray:
    """TFI with the edge rule documented in spk2img.runtime.stream.TFIStream."""
    t, h, w = frames.shape
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            prev = [i for i in range(0, k + 1) if frames[i, y, x]]
            nxt = [i for i in range(k + 1, t) if frames[i, y, x]]
            t_prev = prev[-1] if prev else -1
            t_next = nxt[0] if nxt else t
            out[y, x] = min(1.0, 1.0 / (0.6 * (t_next - t_prev)))
    return out
