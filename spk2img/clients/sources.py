"""What the client can upload, turned into ``.dat`` request bodies (docs/format.md).

A source is a path (``.dat`` needs ``height``/``width``; ``.npy``/``.npz`` hold a ``(T, H, W)``
0/1 array), ``.dat`` bytes (need ``height``/``width``), a ``(T, H, W)`` 0/1 array, or an
iterable of frames — each ``(H, W)`` or a batch ``(n, H, W)``, 0/1, upright — such as a live
camera (the async client also takes an async iterable). Files, bytes and arrays have a known
length (sent with ``Content-Length``, so the service can check the centres up front) and can be
sent again on a retry; an iterable is sent chunked as it produces frames.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterable, AsyncIterator, Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from spk2img.errors import InputError
from spk2img.io.spikes import SpikeFormatError, frame_nbytes, pack_frames, read_spikes

CHUNK_BYTES = 1 << 18
"""About how many body bytes one write sends (whole frames for arrays and iterables)."""

Source = str | os.PathLike[str] | bytes | bytearray | memoryview | np.ndarray | Iterable[np.ndarray]
AsyncSource = Source | AsyncIterable[np.ndarray]


class Upload:
    """A spike stream ready to send: frame size ``height x width`` (pixels), body length
    ``nbytes`` (bytes; ``None`` when unknown, sent chunked) and the body chunks themselves."""

    def __init__(
        self,
        height: int,
        width: int,
        nbytes: int | None,
        chunks: Callable[[], Iterator[bytes] | AsyncIterator[bytes]],
    ):
        self.height, self.width, self.nbytes = height, width, nbytes
        self._chunks = chunks

    @property
    def replayable(self) -> bool:
        """Whether :meth:`body` can start over (for a retry)."""
        return True

    def body(self) -> Iterator[bytes] | AsyncIterator[bytes]:
        """The body from its first byte, in chunks of about :data:`CHUNK_BYTES`."""
        return self._chunks()


class LiveUpload(Upload):
    """Frames drawn from an iterator as they come, sent chunked: one chunk per item. Replayable
    until the body draws past the first item (which was read ahead to learn the frame size)."""

    def __init__(self, first: np.ndarray, rest: Iterator[np.ndarray] | AsyncIterator[np.ndarray]):
        first = _frame_batch(first)
        super().__init__(first.shape[1], first.shape[2], None, self._live_chunks)
        self._first, self._rest, self._drawn = first, rest, False

    @property
    def replayable(self) -> bool:
        return not self._drawn

    def _live_chunks(self) -> Iterator[bytes] | AsyncIterator[bytes]:
        if isinstance(self._rest, AsyncIterator):
            return self._async_chunks()
        return self._sync_chunks()

    def _sync_chunks(self) -> Iterator[bytes]:
        yield self._pack(self._first)
        self._drawn = True
        for frames in self._rest:
            yield self._pack(frames)

    async def _async_chunks(self) -> AsyncIterator[bytes]:
        yield self._pack(self._first)
        self._drawn = True
        async for frames in self._rest:
            yield self._pack(frames)

    def _pack(self, frames: np.ndarray) -> bytes:
        frames = _frame_batch(frames)
        if frames.shape[1:] != (self.height, self.width):
            raise SpikeFormatError(
                f"a frame of {frames.shape[1]}x{frames.shape[2]} in a "
                f"{self.height}x{self.width} stream"
            )
        return pack_frames(frames)


def open_upload(source: Source, height: int | None = None, width: int | None = None) -> Upload:
    """The :class:`Upload` for ``source`` (see the module docstring); ``height``/``width`` are
    needed for ``.dat`` sources and otherwise, when given, must match the frames.

    Raises :class:`~spk2img.errors.InputError` (e.g. ``SpikeFormatError``) for a source
    that cannot be a spike stream and ``FileNotFoundError`` for a missing file.
    """
    if isinstance(source, str | os.PathLike):
        path = Path(source)
        if path.suffix.lower() != ".dat":
            return _array_upload(np.asarray(read_spikes(path)), height, width)
        if not path.is_file():
            raise FileNotFoundError(f"no such file: {path}")
        h, w = _dat_size(height, width)
        return Upload(h, w, path.stat().st_size, lambda: _file_chunks(path))
    if isinstance(source, bytes | bytearray | memoryview):
        h, w = _dat_size(height, width)
        data = memoryview(source).cast("B")
        return Upload(h, w, data.nbytes, lambda: _buffer_chunks(data))
    if isinstance(source, np.ndarray):
        return _array_upload(source, height, width)
    if isinstance(source, Iterable):
        frames = iter(source)
        first = next(frames, None)
        if first is None:
            raise SpikeFormatError("the frame iterable yielded no frame")
        return _checked(LiveUpload(first, frames), height, width)
    raise TypeError(
        f"cannot upload a {type(source).__name__}: give a path, .dat bytes, a (T, H, W) array or "
        "an iterable of frames (AsyncClient also takes an async iterable)"
    )


async def open_async_upload(
    source: AsyncSource, height: int | None = None, width: int | None = None
) -> Upload:
    """:func:`open_upload` that also takes an async iterable of frames (its first is awaited);
    other sources are opened in a worker thread (a live iterator's first frame may block)."""
    if isinstance(source, AsyncIterable):
        frames = aiter(source)
        try:
            first = await anext(frames)
        except StopAsyncIteration:
            raise SpikeFormatError("the frame iterable yielded no frame") from None
        return _checked(LiveUpload(first, frames), height, width)
    return await asyncio.to_thread(open_upload, source, height, width)


def _dat_size(height: int | None, width: int | None) -> tuple[int, int]:
    if height is None or width is None:
        raise InputError(
            ".dat spike streams have no header: give height and width "
            "(the PKU camera's are 250 and 400)"
        )
    frame_nbytes(height, width)  # checks the size
    return int(height), int(width)


def _array_upload(frames: np.ndarray, height: int | None, width: int | None) -> Upload:
    if frames.ndim != 3 or frames.size == 0:
        raise SpikeFormatError(f"a spike array must be a non-empty (T, H, W), got {frames.shape}")
    t, h, w = frames.shape
    per_chunk = max(1, CHUNK_BYTES // frame_nbytes(h, w))

    def chunks() -> Iterator[bytes]:
        for start in range(0, t, per_chunk):
            yield pack_frames(frames[start : start + per_chunk])

    return _checked(Upload(h, w, t * frame_nbytes(h, w), chunks), height, width)


def _checked(upload: Upload, height: int | None, width: int | None) -> Upload:
    if height not in (None, upload.height) or width not in (None, upload.width):
        raise SpikeFormatError(
            f"height x width {height}x{width} given for frames of {upload.height}x{upload.width}"
        )
    return upload


def _frame_batch(frames: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(n, H, W)`` -> ``(n, H, W)``."""
    frames = np.asarray(frames)
    if frames.ndim not in (2, 3):
        raise SpikeFormatError(f"a frame must be (H, W) or a batch (n, H, W), got {frames.shape}")
    return frames[None] if frames.ndim == 2 else frames


def _file_chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            yield chunk


def _buffer_chunks(data: memoryview) -> Iterator[bytes]:
    for start in range(0, data.nbytes, CHUNK_BYTES):
        yield bytes(data[start : start + CHUNK_BYTES])
