"""Choosing output centres and the frame windows around them (one window selector for all).

A centre ``k`` with window ``w`` (odd) needs frames ``k - w//2 .. k + w//2`` of a stream of
``T`` frames; the network's window is its geometry's
(:attr:`~spk2img.model.config.Geometry.window_frames`, 41 frames ``k-20 .. k+20`` as published).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from spk2img.errors import InputError

MAX_BINNING = 64
"""The most stream frames merged into one network frame (a window of 41 x 64 = 2,624 frames
for the published network)."""


class WindowError(InputError):
    """A centre without a full window, or a malformed centres/stride request."""


def check_window(window: int) -> int:
    """Return ``window`` if it is a positive odd integer, else raise :class:`WindowError`."""
    if int(window) != window or window < 1 or window % 2 == 0:
        raise WindowError(f"window must be a positive odd number of frames, got {window}")
    return int(window)


def check_binning(binning: int) -> int:
    """Return ``binning`` (stream frames merged into each of the network's frames) if it is an
    integer in 1 .. :data:`MAX_BINNING`, else raise :class:`WindowError`."""
    if int(binning) != binning or not 1 <= binning <= MAX_BINNING:
        raise WindowError(f"binning must be an integer from 1 to {MAX_BINNING}, got {binning}")
    return int(binning)


def net_window(window_frames: int, binning: int = 1) -> int:
    """Stream frames a network's window spans when each of its ``window_frames`` (odd) frames
    merges ``binning`` stream frames: ``window_frames * binning``, plus one for an even
    ``binning`` so that the window stays centred (odd); that extra last frame is not used."""
    return check_window(window_frames) * check_binning(binning) | 1


MAX_CENTER = 2**62
"""The largest centre (a frame index) that can be asked for: one beyond 64-bit indices is
refused as such, not overflowed."""


def parse_centers(text: str) -> list[int]:
    """Parse ``"40,80,120"`` into ``[40, 80, 120]`` (raises :class:`WindowError`)."""
    try:
        centers = [int(part) for part in text.split(",") if part.strip() != ""]
    except ValueError as exc:
        raise WindowError(f"centers must be comma-separated integers, got {text!r}") from exc
    if not centers:
        raise WindowError("centers must name at least one frame")
    beyond = [c for c in centers if abs(c) > MAX_CENTER]
    if beyond:
        raise WindowError(f"centre {beyond[0]} is beyond any stream (at most {MAX_CENTER})")
    return centers


class CenterPlan:
    """The centres a request wants: an explicit list or every ``stride``-th with a full window.

    ``window`` (odd) is the frames a centre needs: ``k - window//2 .. k + window//2``.
    """

    def __init__(
        self, window: int, centers: Sequence[int] | None = None, stride: int | None = None
    ):
        self.window = check_window(window)
        self.half = self.window // 2
        if centers is not None and stride is not None:
            raise WindowError("give centers or stride, not both")
        if centers is None and stride is None:
            raise WindowError("give centers or stride")
        if stride is not None and (int(stride) != stride or stride < 1):
            raise WindowError(f"stride must be a positive integer, got {stride}")
        self.stride = None if stride is None else int(stride)
        self.centers = None
        if centers is not None:
            self.centers = np.unique(np.asarray(list(centers), dtype=np.int64))
            if self.centers.size == 0:
                raise WindowError("no centres requested")
            if self.centers[0] < self.half:
                raise WindowError(
                    f"centre {int(self.centers[0])} has no full {self.window}-frame window "
                    f"(the first valid centre is {self.half})"
                )

    @classmethod
    def parse(
        cls, window: int, centers: str | None = None, stride: int | None = None
    ) -> CenterPlan:
        """Build a plan from the text forms the CLI and HTTP API take (``"40,80,120"``)."""
        return cls(window, None if centers is None else parse_centers(centers), stride)

    def wants(self, k: int) -> bool:
        """Whether centre ``k`` is requested (ignoring whether the stream is long enough)."""
        if self.centers is not None:
            i = np.searchsorted(self.centers, k)
            return bool(i < self.centers.size and self.centers[i] == k)
        return k >= self.half and (k - self.half) % self.stride == 0

    def centers_for(self, n_frames: int) -> np.ndarray:
        """All centres this plan yields on a stream of ``n_frames`` frames, checked, ``(N,) int64``.

        Raises :class:`WindowError` when a requested centre (or, for a stride, any centre) has
        no full window: call it up front when the stream's length is known.
        """
        if n_frames < self.window:
            raise WindowError(
                f"a stream of {n_frames} frames is shorter than the {self.window}-frame window"
            )
        last = n_frames - 1 - self.half
        if self.centers is None:
            return np.arange(self.half, last + 1, self.stride, dtype=np.int64)
        if self.centers[-1] > last:
            raise WindowError(
                f"centre {int(self.centers[-1])} has no full {self.window}-frame window in a "
                f"stream of {n_frames} frames (valid centres: {self.half} .. {last})"
            )
        return self.centers
