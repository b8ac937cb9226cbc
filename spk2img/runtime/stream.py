"""Streaming reconstruction: feed frames as they arrive, get ``(centre, image)`` pairs back.

One implementation serves the CLI (which reads files in chunks), the service (which decodes
uploads incrementally) and the array helpers in :mod:`spk2img.runtime.classical`, so local and
remote results are the same by construction. Memory stays bounded by the window, not the
stream: a reconstructor keeps the last ``window`` frames at most.

Centres are emitted in ascending order, each as soon as its last needed frame has arrived.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from spk2img.io.light import SPIKE_RATE
from spk2img.io.spikes import as_spike_array
from spk2img.runtime.windows import CenterPlan, WindowError

Frame = tuple[int, np.ndarray]  # (centre index, (H, W) float32 linear intensity in [0, 1])


class StreamingReconstructor(ABC):
    """Base class: frames in by :meth:`push`, finished centres out; :meth:`close` ends the stream.

    Subclasses see every frame once, in order, through :meth:`_on_frame`, and report finished
    centres. ``window`` is how many frames a centre needs (TFP's window, or the network's).
    """

    def __init__(self, height: int, width: int, plan: CenterPlan):
        self.height, self.width, self.plan = height, width, plan
        self.frames_seen = 0

    @property
    def window(self) -> int:
        return self.plan.window

    def push(self, frames: np.ndarray) -> list[Frame]:
        """Feed ``(n, H, W)`` uint8 0/1 frames; return the centres they completed."""
        if frames.ndim != 3 or frames.shape[1:] != (self.height, self.width):
            raise WindowError(
                f"frames of shape {frames.shape[1:]} fed to a {self.height}x{self.width} stream"
            )
        done: list[Frame] = []
        for frame in frames:
            done.extend(self._on_frame(self.frames_seen, frame))
            self.frames_seen += 1
        done.extend(self._flush())
        return done

    def close(self) -> list[Frame]:
        """End the stream: return the centres still owed; raise :class:`WindowError` if a
        requested centre has no full window (or the stream is shorter than one window)."""
        self.plan.centers_for(self.frames_seen)
        return self._flush() + self._finish()

    @abstractmethod
    def _on_frame(self, index: int, frame: np.ndarray) -> list[Frame]:
        """Take frame ``index`` (``(H, W)`` uint8); return centres finished by it."""

    def _flush(self) -> list[Frame]:
        """Finish work batched during :meth:`push` (the network batches its windows)."""
        return []

    def _finish(self) -> list[Frame]:
        """Centres owed at the end of the stream (TFI's pixels that never fire again)."""
        return []


class WindowedReconstructor(StreamingReconstructor):
    """Keeps the last ``window`` frames; a centre is due when its last frame arrives."""

    def __init__(self, height: int, width: int, plan: CenterPlan):
        super().__init__(height, width, plan)
        self._frames: deque[np.ndarray] = deque(maxlen=plan.window)

    def _on_frame(self, index: int, frame: np.ndarray) -> list[Frame]:
        leaving = self._frames[0] if len(self._frames) == self.window else None
        self._frames.append(frame)
        self._slide(frame, leaving)
        k = index - self.plan.half
        if k >= self.plan.half and self.plan.wants(k):
            return self._due(k)
        return []

    def _slide(self, entering: np.ndarray, leaving: np.ndarray | None) -> None:
        """Update running state as one frame enters the window and (maybe) one leaves."""

    @abstractmethod
    def _due(self, k: int) -> list[Frame]:
        """Centre ``k``'s window (``self._frames``) is complete."""


class TFPStream(WindowedReconstructor):
    """TFP (docs/format.md): ``mean(frames k-w//2 .. k+w//2) / 0.6``, clipped to [0, 1].

    A running spike count slides with the stream: O(1) work per pixel per frame.
    """

    def __init__(self, height: int, width: int, plan: CenterPlan):
        super().__init__(height, width, plan)
        self._count = np.zeros((height, width), np.int32)

    def _slide(self, entering: np.ndarray, leaving: np.ndarray | None) -> None:
        self._count += entering
        if leaving is not None:
            self._count -= leaving

    def _due(self, k: int) -> list[Frame]:
        return [(k, tfp_image(self._count, self.window))]


def tfp_image(count: np.ndarray, window: int) -> np.ndarray:
    """TFP from ``(H, W)`` spike counts over ``window`` frames: ``count / (0.6 * window)``
    clipped to [0, 1], float32."""
    image = count.astype(np.float32) / np.float32(window * SPIKE_RATE)
    return np.clip(image, 0.0, 1.0)


Predictor = Callable[[np.ndarray], np.ndarray]
"""``(B, F, H, W) float32`` 0/1 windows of the network's ``F`` frames (its geometry's
``window_frames``, 41 as published) -> ``(B, H, W) float32`` linear intensity in [0, 1]."""


class NetStream(WindowedReconstructor):
    """The network on every due window, batched ``max_batch`` windows at a time.

    ``plan.window`` is the stream frames a window spans: the network's ``F`` frames
    (:func:`~spk2img.runtime.windows.net_window`). With ``binning`` K > 1 (dim streams) it spans
    ``F * K`` (+1) stream frames and each of the network's frames is the union of K consecutive
    ones (a spike where any fired), as a camera with a K times longer frame would film it: a dim
    pixel fires K times as often per network frame, so the network sees the light it was trained
    on; the image is divided by K back to the stream's intensity scale (pixels brighter than 1/K
    saturate).
    """

    def __init__(
        self,
        height: int,
        width: int,
        plan: CenterPlan,
        predict: Predictor,
        max_batch: int = 1,
        binning: int = 1,
    ):
        super().__init__(height, width, plan)
        self.predict, self.max_batch, self.binning = predict, max_batch, binning
        self._batch: list[tuple[int, np.ndarray]] = []

    def _due(self, k: int) -> list[Frame]:
        self._batch.append((k, bin_frames(np.stack(self._frames), self.binning)))
        return self._flush() if len(self._batch) >= self.max_batch else []

    def _flush(self) -> list[Frame]:
        if not self._batch:
            return []
        centers = [k for k, _ in self._batch]
        windows = np.stack([w for _, w in self._batch]).astype(np.float32)
        self._batch = []
        images = self.predict(windows)
        if self.binning > 1:
            images = images / np.float32(self.binning)
        return list(zip(centers, images, strict=True))


def net_input(spikes, center: int, window: int, binning: int = 1) -> np.ndarray:
    """The network's ``(F, H, W)`` 0/1 frames for centre ``center`` of a ``(T, H, W)`` stream
    (an array or a memory-mapped stream): the ``window`` stream frames around it
    (:func:`~spk2img.runtime.windows.net_window`), merged by :func:`bin_frames`."""
    half = window // 2
    return bin_frames(np.asarray(spikes[center - half : center + half + 1]), binning)


def bin_frames(window: np.ndarray, binning: int) -> np.ndarray:
    """The network's ``(F, H, W)`` frames from a ``(net_window(F, binning), H, W)`` 0/1 window:
    frame ``j`` is 1 where any of stream frames ``j * binning .. (j + 1) * binning - 1`` fired
    (the window's extra last frame, for an even ``binning``, is dropped)."""
    if binning == 1:
        return window
    frames = len(window) // binning
    merged = window[: frames * binning].reshape(frames, binning, *window.shape[1:])
    return merged.max(axis=1)


class TFIStream(StreamingReconstructor):
    """TFI (docs/format.md): ``1 / (0.6 * (t_next - t_prev))`` in [0, 1], over the whole stream.

    ``t_prev`` is the last spike at or before ``k``, ``t_next`` the first after ``k``. A centre is
    emitted once its window has arrived and every pixel has fired after it, else at the end of the
    stream, where a side with no spike counts as the distance to the stream's edge
    (``k - t_prev = k + 1``, ``t_next - k = T - k``): finite, in [0, 1], dark where spikes are rare.
    """

    def __init__(self, height: int, width: int, plan: CenterPlan):
        super().__init__(height, width, plan)
        self._last_spike = np.full((height, width), -1, np.int32)
        self._pending: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # k, t_prev, t_next

    @property
    def pending_centres(self) -> int:
        """Centres seen and not yet emitted; each holds two ``(H, W)`` int32 maps (8 B a pixel)."""
        return len(self._pending)

    def _on_frame(self, index: int, frame: np.ndarray) -> list[Frame]:
        fired = frame.astype(bool)
        for _, _, t_next in self._pending:
            t_next[fired & (t_next < 0)] = index
        self._last_spike[fired] = index
        if self.plan.wants(index):
            self._pending.append(
                (index, self._last_spike.copy(), np.full_like(self._last_spike, -1))
            )
        done = []
        while self._pending:
            k, t_prev, t_next = self._pending[0]
            if index < k + self.plan.half or (t_next < 0).any():
                break
            self._pending.popleft()
            done.append((k, _tfi_image(t_next - t_prev)))
        return done

    def _finish(self) -> list[Frame]:
        done = []
        last = self.frames_seen - 1 - self.plan.half  # centres past it have no full window
        for k, t_prev, t_next in self._pending:
            if k > last:
                break
            t_next = np.where(t_next < 0, self.frames_seen, t_next)
            done.append((k, _tfi_image(t_next - t_prev)))
        self._pending.clear()
        return done


def _tfi_image(interval: np.ndarray) -> np.ndarray:
    """``1 / (0.6 * interval)`` clipped to [0, 1]; ``interval`` >= 1 frames, ``(H, W)``."""
    return np.clip(1.0 / (SPIKE_RATE * interval.astype(np.float32)), 0.0, 1.0)


def run_stream(recon: StreamingReconstructor, chunks: Iterable[np.ndarray]) -> Iterator[Frame]:
    """Push every ``(n, H, W)`` chunk through ``recon`` and yield ``(centre, image)`` pairs."""
    for chunk in chunks:
        yield from recon.push(chunk)
    yield from recon.close()


def frame_chunks(spikes, chunk: int = 256) -> Iterator[np.ndarray]:
    """Slices of ``chunk`` frames of a ``(T, H, W)`` array or memory-mapped stream, in order,
    as ``uint8``; a value other than 0/1 raises :class:`~spk2img.io.spikes.SpikeFormatError`
    (never cast: 2 or 0.5 is not a spike)."""
    for start in range(0, len(spikes), chunk):
        yield as_spike_array(np.asarray(spikes[start : start + chunk]))


def collect(frames: Iterable[Frame], height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Stack ``(centre, image)`` pairs into ``frames (N, H, W) float32``, ``centers (N,) int64``."""
    pairs = list(frames)
    images = np.stack([img for _, img in pairs]) if pairs else np.zeros((0, height, width))
    centers = np.asarray([k for k, _ in pairs], dtype=np.int64)
    return images.astype(np.float32, copy=False), centers
